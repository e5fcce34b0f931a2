"""Every path in a job folder, spelled once. Pipeline, report, re-rendering and the service's artifacts all
read and write through :class:`JobLayout`; ``tests/job/test_layout.py`` fails when a path is spelled elsewhere.

Job folder::

    job/
      job.json          the options (written once by whoever creates the job)
      images/           ingest: validated, upright images
      ingest.json       ingest: what was taken and what was refused
      scene/            sfm: images/ (undistorted) + sparse/0 (PINHOLE) + distorted/
      classify.json     classify: water type, probabilities, index w, controller settings
      train/            train: latest.pt (the resume point), train.json (metrics, speed-vs-error, quality),
                        selection.json (the mode probe, mode auto), config.json (the resolved TrainConfig)
      evaluate.json     evaluate: held-out scores, restoration against ground truth, timings, the curve
      evaluate/         evaluate: renders from the true cameras (jobs with ground truth)
      output/           export: reconstruction.ply, restored/, with_water/, attenuation/, backscatter/, depth/,
                        report.json, report.html, speed_vs_error.png
      .stages/<stage>.json   completion markers (config hash + result)
      .artifacts.json   the service's checksum cache of the downloadable files
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# The per-view image folders of the export (the last two only in medium modes).
EXPORT_FOLDERS: tuple[str, ...] = ("restored", "with_water", "depth", "attenuation", "backscatter")


@dataclass(frozen=True)
class JobLayout:
    """The paths of one job folder ``root``."""

    root: Path

    def __init__(self, root: str | Path) -> None:
        object.__setattr__(self, "root", Path(root))

    # ------------------------------------------------------------------ job and ingest
    @property
    def options(self) -> Path:
        return self.root / "job.json"

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def ingest(self) -> Path:
        return self.root / "ingest.json"

    # ------------------------------------------------------------------ sfm, classify
    @property
    def scene(self) -> Path:
        return self.root / "scene"

    @property
    def classify(self) -> Path:
        """The classifier's water decision (a generated scene's ``water.json`` is its true water, not this)."""
        return self.root / "classify.json"

    # ------------------------------------------------------------------ train
    @property
    def train(self) -> Path:
        return self.root / "train"

    @property
    def checkpoint(self) -> Path:
        return self.train / "latest.pt"

    @property
    def train_result(self) -> Path:
        return self.train / "train.json"

    @property
    def selection(self) -> Path:
        return self.train / "selection.json"

    @property
    def train_config(self) -> Path:
        return self.train / "config.json"

    # ------------------------------------------------------------------ evaluate
    @property
    def evaluate(self) -> Path:
        return self.root / "evaluate.json"

    @property
    def evaluate_renders(self) -> Path:
        return self.root / "evaluate"

    # ------------------------------------------------------------------ export
    @property
    def output(self) -> Path:
        return self.root / "output"

    @property
    def ply(self) -> Path:
        return self.output / "reconstruction.ply"

    @property
    def report_json(self) -> Path:
        return self.output / "report.json"

    @property
    def report_html(self) -> Path:
        return self.output / "report.html"

    @property
    def curve_png(self) -> Path:
        return self.output / "speed_vs_error.png"

    def export_folder(self, name: str) -> Path:
        if name not in EXPORT_FOLDERS:
            raise ValueError(f"unknown export folder {name!r}; one of {EXPORT_FOLDERS}")
        return self.output / name

    # ------------------------------------------------------------------ bookkeeping
    @property
    def markers(self) -> Path:
        return self.root / ".stages"

    def marker(self, stage: str) -> Path:
        return self.markers / f"{stage}.json"

    @property
    def artifacts_cache(self) -> Path:
        return self.root / ".artifacts.json"

    def relative(self, path: Path) -> str:
        """``path`` as the POSIX path inside the job folder (how artifacts are named)."""
        return path.relative_to(self.root).as_posix()
