"""Every path in a job folder, spelled once. Pipeline, report, re-rendering, the service and the worker all
read and write through :class:`JobLayout`; ``tests/job/test_layout.py`` fails when a name is spelled elsewhere.

Job folder::

    job/
      job.json          the options (written once by whoever creates the job)
      images/           ingest: validated, upright images (upload/ holds an archive while ingest unpacks it)
      ingest.json       ingest: what was taken and what was refused
      records/          ingest: the CSV files that came with the images (telemetry logs for the survey stage)
      scene/            sfm: images/ (undistorted) + sparse/0 (PINHOLE) + distorted/
      classify.json     classify: water type, probabilities, index w, controller settings
                        (water.json in job folders written before the rename; see legacy_classify)
      train/            train: latest.pt (the resume point), train.json (metrics, speed-vs-error, quality),
                        selection.json (the mode probe, mode auto), config.json (the resolved TrainConfig),
                        recovery.json + collapsed.pt (a first attempt that lost its scene)
      evaluate.json     evaluate: held-out scores, restoration against ground truth, timings, the curve
      evaluate/         evaluate: true_camera/ renders from the true cameras (jobs with ground truth)
      restore.json      restore: per photo what was restored (surface share, capped gain, clipping, seconds),
                        and, with ground truth, the full-resolution scores
      output/           restore: restored/ (the input photos de-watered: same names, sizes, formats, metadata),
                        confidence/ (one 8-bit map per photo: 0 = not restored, 255 = full confidence);
                        export: reconstruction.ply, reconstruction.spz (the same Gaussians, SPZ),
                        renders/{restored,with_water,attenuation,backscatter,depth}/
                        (the model's renders at the training resolution), report.json, report.html,
                        speed_vs_error.png
      survey.json       survey: the metric scale (source, per-frame agreement), the frame (CRS, georeference fit),
                        the products' grid, area and reef-structure numbers
      output/survey/    survey: ortho.tif (the restored photos as an orthomosaic), ortho_water.tif (the photos
                        as taken), ortho_confidence.tif, dem.tif (height above the survey plane), previews
                        (ortho.jpg, ortho_water.jpg, dem_hillshade.png); Cloud-Optimized GeoTIFFs
      .stages/<stage>.json   completion markers (config hash + result)
    written by the service:
      manifest.json     the job record (a folder without one is an upload still streaming)
      log.txt           the job's log, append-only
      input/            the uploaded archive (input/archive) or a survey set's copied images
      source.json       the input's name as the client knows it (the report shows it)
      .artifacts.json   the checksum cache of the downloadable files

A generated scene (``pipeline.synth``) is another folder with its own names: its ``water.json`` is the true
water (:data:`pipeline.synth.water.TRUE_WATER_FILE`), unrelated to the job's ``classify.json``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# The per-view folders of the model's renders under output/renders/ (the last two only in medium modes; in mode
# 3dgs "restored" is not written: a model without water has nothing to restore).
RENDER_FOLDERS: tuple[str, ...] = ("restored", "with_water", "depth", "attenuation", "backscatter")

# The train folder's files by name. The trainer, its collapse guard and the mode probe are handed the folder
# (tests and benches train into any folder) and join these names to it; in a job it is JobLayout.train.
CHECKPOINT_NAME = "latest.pt"
SELECTION_NAME = "selection.json"
RECOVERY_NAME = "recovery.json"
COLLAPSED_NAME = "collapsed.pt"


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
    def unpacked(self) -> Path:
        """Where ingest unpacks an archive source (removed once the images are taken)."""
        return self.root / "upload"

    @property
    def ingest(self) -> Path:
        return self.root / "ingest.json"

    @property
    def records(self) -> Path:
        """The survey's logs that came with the images (CSV files, flattened names as images/ has them)."""
        return self.root / "records"

    # ------------------------------------------------------------------ sfm, classify
    @property
    def scene(self) -> Path:
        return self.root / "scene"

    @property
    def classify(self) -> Path:
        """The classifier's water decision (a generated scene's ``water.json`` is its true water, not this)."""
        return self.root / "classify.json"

    @property
    def legacy_classify(self) -> Path:
        """Where job folders written before the rename keep the classifier's decision. Their classify marker
        matches (the stage's options did not change), so the stage is skipped on resume and never writes
        :attr:`classify`: readers fall back to this file, or a resumed job would train without its water."""
        return self.root / "water.json"

    @property
    def classify_written(self) -> Path | None:
        """The classifier's decision as this folder holds it: :attr:`classify`, else :attr:`legacy_classify`,
        else None (not classified)."""
        return next((p for p in (self.classify, self.legacy_classify) if p.is_file()), None)

    # ------------------------------------------------------------------ train
    @property
    def train(self) -> Path:
        return self.root / "train"

    @property
    def checkpoint(self) -> Path:
        return self.train / CHECKPOINT_NAME

    @property
    def train_result(self) -> Path:
        return self.train / "train.json"

    @property
    def selection(self) -> Path:
        return self.train / SELECTION_NAME

    @property
    def train_config(self) -> Path:
        return self.train / "config.json"

    @property
    def recovery(self) -> Path:
        return self.train / RECOVERY_NAME

    @property
    def collapsed(self) -> Path:
        return self.train / COLLAPSED_NAME

    # ------------------------------------------------------------------ evaluate
    @property
    def evaluate(self) -> Path:
        return self.root / "evaluate.json"

    @property
    def evaluate_renders(self) -> Path:
        return self.root / "evaluate"

    @property
    def true_camera(self) -> Path:
        """Renders from the true cameras (with_water/, restored/), jobs with ground truth only."""
        return self.evaluate_renders / "true_camera"

    @property
    def previews(self) -> Path:
        """Small JPEGs of the photos and their restored versions that the dashboard shows (the service makes them
        on first request: ``previews/<original|restored>/<stem>.jpg``); not results, never downloaded."""
        return self.root / ".previews"

    # ------------------------------------------------------------------ export
    @property
    def output(self) -> Path:
        return self.root / "output"

    @property
    def ply(self) -> Path:
        return self.output / "reconstruction.ply"

    @property
    def spz(self) -> Path:
        """The reconstruction as SPZ (``pipeline.splat.spz``): the same Gaussians as ``ply``, compressed."""
        return self.output / "reconstruction.spz"

    @property
    def cameras(self) -> Path:
        """The training cameras in the PLY's frame, for the dashboard's 3D viewer (pipeline/export/cameras.py)."""
        return self.output / "cameras.json"

    @property
    def report_json(self) -> Path:
        return self.output / "report.json"

    @property
    def report_html(self) -> Path:
        return self.output / "report.html"

    @property
    def curve_png(self) -> Path:
        return self.output / "speed_vs_error.png"

    @property
    def renders(self) -> Path:
        """The model's renders of every view at the training resolution (one sub-folder per RENDER_FOLDERS)."""
        return self.output / "renders"

    def render_folder(self, name: str) -> Path:
        if name not in RENDER_FOLDERS:
            raise ValueError(f"unknown render folder {name!r}; one of {RENDER_FOLDERS}")
        return self.renders / name

    # ------------------------------------------------------------------ restore (the photos themselves)
    @property
    def restore_result(self) -> Path:
        return self.root / "restore.json"

    @property
    def restored(self) -> Path:
        """The input photos de-watered, at their own size, lens geometry, name and format."""
        return self.output / "restored"

    @property
    def confidence(self) -> Path:
        """One confidence map per restored photo (``<stem>.png``)."""
        return self.output / "confidence"

    # ------------------------------------------------------------------ survey products
    @property
    def survey_result(self) -> Path:
        return self.root / "survey.json"

    @property
    def survey(self) -> Path:
        """The survey products (:mod:`pipeline.survey`): orthomosaics, elevation model, previews."""
        return self.output / "survey"

    @property
    def ortho(self) -> Path:
        return self.survey / "ortho.tif"

    @property
    def ortho_water(self) -> Path:
        return self.survey / "ortho_water.tif"

    @property
    def ortho_confidence(self) -> Path:
        return self.survey / "ortho_confidence.tif"

    @property
    def dem(self) -> Path:
        return self.survey / "dem.tif"

    @property
    def ortho_preview(self) -> Path:
        return self.survey / "ortho.jpg"

    @property
    def ortho_water_preview(self) -> Path:
        return self.survey / "ortho_water.jpg"

    @property
    def hillshade_preview(self) -> Path:
        return self.survey / "dem_hillshade.png"

    # ------------------------------------------------------------------ bookkeeping
    @property
    def markers(self) -> Path:
        return self.root / ".stages"

    def marker(self, stage: str) -> Path:
        return self.markers / f"{stage}.json"

    # ------------------------------------------------------------------ the service's files
    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def log(self) -> Path:
        return self.root / "log.txt"

    @property
    def input(self) -> Path:
        return self.root / "input"

    @property
    def upload(self) -> Path:
        """The uploaded archive as received."""
        return self.input / "archive"

    @property
    def source_name(self) -> Path:
        return self.root / "source.json"

    @property
    def artifacts_cache(self) -> Path:
        return self.root / ".artifacts.json"

    def relative(self, path: Path) -> str:
        """``path`` as the POSIX path inside the job folder (how artifacts are named)."""
        return path.relative_to(self.root).as_posix()
