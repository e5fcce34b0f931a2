"""What a user chooses for a job (CLI flags, API form fields) and what a runner hands the stages. Torch-free."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.ingest.intake import IngestConfig


class JobCancelled(RuntimeError):
    """The job's ``should_cancel`` said stop; completed stages and checkpoints are kept."""


# "auto": a short probe on the training views picks one of the others and sizes the model (pipeline.train.probe).
JOB_MODES: tuple[str, ...] = ("auto", "3dgs", "homogeneous", "dualphys")


@dataclass
class JobOptions:
    """What a user chooses for a job (CLI flags / API form fields)."""

    source: str = ""  # archive file or image folder to ingest
    # What a client may set (the API's form fields are built from these: service/options.py; "help" is their
    # description there).
    preset: str = field(default="fast", metadata={"help": "training preset: fast | balanced | paper"})
    mode: str = field(default="auto", metadata={
        "help": "reconstruction mode: auto (a short probe picks) | 3dgs | homogeneous | dualphys"})
    max_width: int = field(default=400, metadata={
        "help": "images wider than this train at a downscale"})  # an integer one (CPU budget)
    metric_scale: float | None = field(default=None, metadata={"help": "metres per scene unit, when known"})
    iterations: int | None = field(default=None, metadata={"help": "override the preset's iteration count"})
    seed: int = field(default=0, metadata={"help": "the seed of SfM and training"})
    # A generated scene folder (pipeline.synth.procedural) to score against; unset: found next to an ``images``
    # source folder when that sits in a generated scene (pipeline.synth.ground_truth).
    ground_truth: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in JOB_MODES:
            raise ValueError(f"unknown mode {self.mode!r}; choose from {', '.join(JOB_MODES)}")

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> JobOptions:
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown job options: {sorted(unknown)}")
        return cls(**d)


@dataclass
class StageContext:
    """Callbacks a runner (CLI, worker) hands to the stages."""

    on_progress: Callable[[str, float, str], None] = lambda stage, fraction, message: None
    should_cancel: Callable[[], bool] = lambda: False
    device: str = "cpu"
    extra: dict[str, Any] = field(default_factory=dict)
    # the deployment's ingest limits (archive limits, minimum image count); None: pipeline.ingest's defaults
    ingest: IngestConfig | None = None
