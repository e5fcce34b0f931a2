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
COLOUR_SPACES: tuple[str, ...] = ("srgb", "linear")
# How the restore stage writes the de-watered photos (pipeline.restore).
RESTORE_FORMATS: tuple[str, ...] = ("auto", "tiff16")


@dataclass
class JobOptions:
    """What a user chooses for a job (CLI flags / API form fields)."""

    source: str = ""  # archive file or image folder to ingest
    # What a client may set (the API's form fields are built from these: service/jobs/options.py; "help" is their
    # description there).
    preset: str = field(default="fast", metadata={"help": "training preset: fast | balanced | paper"})
    mode: str = field(default="auto", metadata={
        "help": "reconstruction mode: auto (a short probe picks) | 3dgs | homogeneous | dualphys"})
    max_width: int = field(default=400, metadata={
        "help": "images wider than this train at a downscale"})  # an integer one (CPU budget)
    metric_scale: float | None = field(default=None, metadata={"help": "metres per scene unit, when known"})
    iterations: int | None = field(default=None, metadata={"help": "override the preset's iteration count"})
    seed: int = field(default=0, metadata={"help": "the seed of SfM and training"})
    # "linear" by measurement (docs/DECISIONS.md, "Colour space"): a camera's water acts on light, which the camera
    # then encodes; our generator's default scenes apply it to encoded values and need "srgb"
    colour_space: str = field(default="linear", metadata={
        "help": "where the water physics runs: linear (default: on linear light, the photos decoded with the "
                "sRGB curve and the results encoded back, as a camera's JPEGs need) | srgb (on the encoded "
                "values)"})
    restore_format: str = field(default="auto", metadata={
        "help": "the restored photos' files: auto (each as its input: 8-bit JPEG or PNG) | tiff16 (16-bit TIFF)"})
    max_gain: float = field(default=8.0, metadata={
        "help": "cap on the restoration's per-channel gain 1/A (where the water let less light through, noise "
                "would be amplified more; those pixels get low confidence)"})
    # Survey products (pipeline.survey): the orthomosaic and elevation model, in metres when the survey says how
    ortho: bool = field(default=True, metadata={
        "help": "make the survey products: a de-watered orthomosaic, the same with water, and an elevation model "
                "(Cloud-Optimized GeoTIFFs)"})
    ortho_gsd: float | None = field(default=None, metadata={
        "help": "the products' ground resolution in metres per pixel (scene units without a metric scale); "
                "default: the photos' own at the median range"})
    telemetry: str | None = field(default=None, metadata={
        "help": "a CSV of per-frame records (file, camera_to_bottom_m, lat, lon; AIMS frames.csv columns): a "
                "path, or a file name in the uploaded archive or survey folder; EXIF is read without it"})
    scale_bar: str | None = field(default=None, metadata={
        "help": "known lengths marked in the photos, 'PHOTO:X1,Y1:X2,Y2:METRES', several joined by ';' "
                "(pixel positions in the photo as uploaded)"})
    # A generated scene folder (pipeline.synth.procedural) to score against; unset: found next to an ``images``
    # source folder when that sits in a generated scene (pipeline.synth.ground_truth).
    ground_truth: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in JOB_MODES:
            raise ValueError(f"unknown mode {self.mode!r}; choose from {', '.join(JOB_MODES)}")
        if self.colour_space not in COLOUR_SPACES:
            raise ValueError(f"unknown colour_space {self.colour_space!r}; choose from "
                             f"{', '.join(COLOUR_SPACES)}")
        if self.restore_format not in RESTORE_FORMATS:
            raise ValueError(f"unknown restore_format {self.restore_format!r}; choose from "
                             f"{', '.join(RESTORE_FORMATS)}")
        if not self.max_gain >= 1.0:
            raise ValueError(f"max_gain is a gain cap >= 1, got {self.max_gain}")
        if self.ortho_gsd is not None and not self.ortho_gsd > 0:
            raise ValueError(f"ortho_gsd is a ground resolution > 0, got {self.ortho_gsd}")
        parse_scale_bars(self.scale_bar)  # raises ValueError with the reason

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> JobOptions:
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown job options: {sorted(unknown)}")
        return cls(**d)


@dataclass(frozen=True)
class ScaleBar:
    """A known length marked in one photo: two pixel positions in the photo as uploaded (column, row from its
    top-left corner, as an image viewer shows them) and the metres between the two points on the seabed."""

    photo: str
    a: tuple[float, float]
    b: tuple[float, float]
    metres: float


def parse_scale_bars(text: str | None) -> list[ScaleBar]:
    """``'PHOTO:X1,Y1:X2,Y2:METRES'`` entries joined by ``';'`` -> scale bars; ValueError says what is wrong."""
    bars = []
    for entry in filter(None, (e.strip() for e in (text or "").split(";"))):
        parts = entry.rsplit(":", 3)
        try:
            photo, a, b, metres = parts
            (x1, y1), (x2, y2) = (tuple(float(v) for v in p.split(",")) for p in (a, b))
            bar = ScaleBar(photo.strip(), (x1, y1), (x2, y2), float(metres))
        except ValueError:
            raise ValueError(f"scale_bar {entry!r}: expected 'PHOTO:X1,Y1:X2,Y2:METRES'") from None
        if not photo.strip() or not bar.metres > 0 or bar.a == bar.b:
            raise ValueError(f"scale_bar {entry!r}: a photo name, two different points and a length > 0 needed")
        bars.append(bar)
    return bars


@dataclass
class StageContext:
    """Callbacks a runner (CLI, worker) hands to the stages."""

    on_progress: Callable[[str, float, str], None] = lambda stage, fraction, message: None
    should_cancel: Callable[[], bool] = lambda: False
    device: str = "cpu"
    extra: dict[str, Any] = field(default_factory=dict)
    # the deployment's ingest limits (archive limits, minimum image count); None: pipeline.ingest's defaults
    ingest: IngestConfig | None = None
