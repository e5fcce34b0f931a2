"""One job = the stages in order, on a job folder. The same functions run from the CLI, a Celery task and tests.

Job folder::

    job/
      job.json          the options (written once by whoever creates the job)
      images/           ingest: validated, upright images
      ingest.json
      scene/            sfm: images/ (undistorted) + sparse/0 (PINHOLE) + distorted/
      water.json        classify: water type, probabilities, index w, controller settings
      train/            train: latest.pt checkpoint (resume point), train.json (metrics, speed-vs-error)
      evaluate.json     evaluate: held-out scores, restoration against ground truth, timings, the curve
      evaluate/         evaluate: renders from the true cameras (jobs with ground truth)
      output/           export: reconstruction.ply, restored/, with_water/, attenuation/, backscatter/, depth/,
                        report.json, report.html, speed_vs_error.png
      .stages/<stage>.json   completion markers (config hash + result)

A stage's config hash covers its own options and the hashes of the stages before it, so changing an upstream
option re-runs everything downstream and nothing else. Every stage takes (job_dir, options, context) and
returns a JSON-able result; :func:`run_job` skips stages whose marker matches.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .stages import config_hash, read_marker, run_marked

log = logging.getLogger(__name__)

STAGES: tuple[str, ...] = ("ingest", "sfm", "classify", "train", "evaluate", "export")


class JobCancelled(RuntimeError):
    """The job's ``should_cancel`` said stop; completed stages and checkpoints are kept."""


# "auto": a short probe on the training views picks one of the others and sizes the model (pipeline.select).
JOB_MODES: tuple[str, ...] = ("auto", "3dgs", "homogeneous", "dualphys")


@dataclass
class JobOptions:
    """What a user chooses for a job (CLI flags / API form fields)."""

    source: str = ""  # archive file or image folder to ingest
    preset: str = "fast"  # training preset: fast | balanced | paper
    mode: str = "auto"  # reconstruction mode, one of JOB_MODES
    max_width: int = 400  # images wider than this are trained at an integer downscale (CPU budget)
    metric_scale: float | None = None  # metres per scene unit, when the user knows it
    iterations: int | None = None  # override the preset's iteration count (tests, quick looks)
    seed: int = 0
    # A generated scene folder (pipeline.scene.synth) to score against; unset: found next to an ``images``
    # source folder when that sits in a generated scene (pipeline.ground_truth).
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


# ---------------------------------------------------------------- the stages


def stage_ingest(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from .ingest import ingest

    return ingest(opts.source, job).to_json()


def stage_sfm(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """pycolmap runs in native code, so a watcher thread turns ``should_cancel`` into its CancellationToken;
    the running step then raises InterruptedError, which becomes JobCancelled."""
    import threading

    import pycolmap

    from .config import SfmConfig
    from .sfm import run_sfm

    token, done = pycolmap.CancellationToken(), threading.Event()

    def watch() -> None:
        while not done.wait(0.25):
            if ctx.should_cancel():
                token.cancel()
                return

    watcher = threading.Thread(target=watch, name="sfm-cancel-watch", daemon=True)
    watcher.start()
    try:
        return run_sfm(job / "images", job / "scene", SfmConfig(seed=opts.seed), cancellation_token=token).to_dict()
    except InterruptedError as e:
        raise JobCancelled(f"cancelled during sfm: {e}") from e
    finally:
        done.set()
        watcher.join()


CLASSIFY_IMAGES = 8  # images (evenly spaced by name) the water classifier averages over


def stage_classify(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from .scene.images import read_image
    from .stages import atomic_write_json
    from .water import classify

    names = sorted(p for p in (job / "images").iterdir() if p.is_file())
    pick = names[:: max(1, len(names) // CLASSIFY_IMAGES)][:CLASSIFY_IMAGES]
    decision = classify([read_image(p) for p in pick]).to_dict()
    atomic_write_json(job / "water.json", decision)
    return decision


def apply_water_decision(cfg, decision: dict) -> None:
    """The controller's settings (paper §5) into a TrainConfig's medium section."""
    m = cfg.medium
    if not m.water_adaptation:
        return
    m.lr_attenuation, m.lr_scattering = decision["lr_attenuation"], decision["lr_scattering"]
    m.alpha_w, m.beta_w = decision["alpha"], decision["beta"]
    m.start_fraction = decision["medium_start_fraction"]
    m.init_optical_depth = tuple(decision.get("init_optical_depth", m.init_optical_depth))  # type: ignore[assignment]


def train_config(opts: JobOptions, width: int, mode: str | None = None):
    """The TrainConfig a job trains with: the preset, the mode (``mode`` replaces the job's, which must be
    given when the job's is "auto"), its seed, the downscale for ``max_width``."""
    from .config import train_preset

    cfg = train_preset(opts.preset)
    if opts.iterations is not None:
        from .config import scaled_train_config

        cfg = scaled_train_config(opts.iterations, checkpoint_every=max(1, opts.iterations // 5),
                                  max_gaussians=300_000)
    cfg.seed = opts.seed
    cfg.mode = mode or opts.mode  # type: ignore[assignment]
    if cfg.mode == "auto":
        raise ValueError("train_config: mode 'auto' must be resolved first (pipeline.select)")
    cfg.downscale = max(1, math.ceil(width / opts.max_width))
    from .train_hooks import curve_every

    cfg.eval_every = curve_every(cfg.iterations)  # the speed-vs-error curve's fixed schedule
    return cfg


def stage_train(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from .scene.loader import load_images, load_scene
    from .scene.split import split_views
    from .stages import atomic_write_json
    from .train import TrainingCancelled
    from .train_guard import train_checked

    scene = load_scene(job / "scene")
    train_views, test_views = split_views(scene.views)
    train_scene = scene.subset(train_views)
    images = load_images(train_scene)
    water = json.loads((job / "water.json").read_text()) if (job / "water.json").exists() else None
    selection = select_mode(job, opts, train_scene, images, water, ctx) if opts.mode == "auto" else None
    cfg = train_config(opts, scene.views[0].camera.width, selection["chosen"] if selection else None)
    if selection is not None:  # the Gaussian budget and SH degree scaled to the scene (pipeline.budget)
        cfg.sh_degree = selection["budget"]["sh_degree"]
        cfg.densify.max_gaussians = selection["budget"]["max_gaussians"]
    if cfg.mode != "3dgs" and water is not None:
        apply_water_decision(cfg, water)
    start = PROBE_SHARE if selection is not None else 0.0
    from .train_hooks import curve_subset

    curve_views = [test_views[i] for i in curve_subset(len(test_views))]  # a few views keep the curve cheap
    test_images = load_images(type(scene)(curve_views, root=scene.root)) if curve_views else []

    def progress(it: int, total: int, metrics: dict) -> None:
        ctx.on_progress("train", start + (1 - start) * it / max(1, total), f"iteration {it}/{total}")

    try:
        res, quality, recovery = train_checked(train_scene, images, cfg, job / "train", test_views=curve_views,
                                               test_images=test_images, on_progress=progress,
                                               should_cancel=ctx.should_cancel, device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(str(e)) from e
    out = {"mode": cfg.mode, "iterations": res.iteration, "metrics": res.metrics, "history": res.history,
           "medium": res.medium,
           "elapsed_s": res.elapsed_s, "n_gaussians": int(res.gaussians["means"].shape[0]),
           "n_train_views": len(train_views), "n_test_views": len(test_views), "downscale": cfg.downscale,
           "curve_views": [v.name for v in curve_views], "quality": quality, "recovery": recovery}
    atomic_write_json(job / "train" / "train.json", out)
    return out


PROBE_SHARE = 0.1  # of the train stage's progress that the mode probe reports (mode auto)


def select_mode(job: Path, opts: JobOptions, scene, images, water: dict | None, ctx: StageContext) -> dict:
    """``--mode auto``: the probe on the training views (``pipeline.select``) -> ``job/train/selection.json``."""
    from .select import select_for_job
    from .train import TrainingCancelled

    base = train_config(opts, scene.views[0].camera.width, "dualphys")  # seed, backend, caps, medium settings
    if water is not None:
        apply_water_decision(base, water)
    try:
        return select_for_job(job / "train", scene, images, base, water=water,
                              on_progress=lambda f, m: ctx.on_progress("train", PROBE_SHARE * f, m),
                              should_cancel=ctx.should_cancel, device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(f"cancelled during the mode probe: {e}") from e


def stage_evaluate(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """Held-out scores, restoration against ground truth where it exists, timings, the speed-vs-error curve
    (``pipeline.evaluate``) -> ``job/evaluate.json``."""
    from .evaluate import evaluate_job
    from .ground_truth import find_ground_truth
    from .stages import atomic_write_json

    gt = find_ground_truth(opts.source, opts.ground_truth)
    res = evaluate_job(job, gt, stages=STAGES[:STAGES.index("evaluate")])
    atomic_write_json(job / "evaluate.json", res)
    return res


def stage_export(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """reconstruction.ply plus restored/, with_water/, attenuation/, backscatter/, depth/ for every input
    view (training and held-out alike), at the resolution training used; then report.json and report.html
    (``pipeline.report``), which read those files."""
    import time

    t0 = time.perf_counter()
    from .checkpoint import load_checkpoint
    from .restore import export_views
    from .scene.loader import load_scene
    from .scene.types import View
    from .splat.ply import export_ply

    state = load_checkpoint(job / "train" / "latest.pt")
    out = job / "output"
    out.mkdir(parents=True, exist_ok=True)
    data = export_ply(state["gaussians"], out / "reconstruction.ply")
    down = int(state["config"].get("downscale", 1))
    views = [View(v.name, v.camera.scaled(1.0 / down), v.R, v.t, v.image_path)
             for v in load_scene(job / "scene").views]
    counts = export_views(state, views, out)
    from .report import write_report

    reports = write_report(job, out, export_s=time.perf_counter() - t0)
    return {"reconstruction.ply": len(data), **counts, "report": [p.name for p in reports]}


STAGE_FUNCTIONS: dict[str, Callable[[Path, JobOptions, StageContext], dict]] = {
    "ingest": stage_ingest, "sfm": stage_sfm, "classify": stage_classify, "train": stage_train,
    "evaluate": stage_evaluate, "export": stage_export,
}
# Which options each stage depends on (beyond the stages before it).
STAGE_OPTIONS: dict[str, tuple[str, ...]] = {
    "ingest": ("source",), "sfm": ("seed",), "classify": (),
    "train": ("preset", "mode", "max_width", "iterations", "seed"),
    "evaluate": ("ground_truth",),
    "export": (),
}


def stage_config(opts: JobOptions, stage: str) -> dict:
    """What a stage's marker hash covers: its options and the chain of the stages before it."""
    i = STAGES.index(stage)
    upstream = config_hash(stage_config(opts, STAGES[i - 1])) if i else None
    return {"stage": stage, "upstream": upstream, **{k: getattr(opts, k) for k in STAGE_OPTIONS[stage]}}


def run_stage(job: Path, stage: str, opts: JobOptions, ctx: StageContext | None = None) -> tuple[dict, bool]:
    """Run one stage unless its marker matches; returns (result, skipped)."""
    ctx = ctx or StageContext()
    if ctx.should_cancel():
        raise JobCancelled(f"cancelled before {stage}")
    ctx.on_progress(stage, 0.0, "started")
    result, skipped = run_marked(job, stage, stage_config(opts, stage),
                                 lambda: STAGE_FUNCTIONS[stage](job, opts, ctx))
    ctx.on_progress(stage, 1.0, "skipped (already done)" if skipped else "done")
    return result, skipped


def run_job(job: str | Path, opts: JobOptions, ctx: StageContext | None = None,
            stages: tuple[str, ...] = STAGES) -> dict[str, dict]:
    """Run the stages in order in ``job``; finished ones (matching markers) are skipped."""
    job = Path(job)
    job.mkdir(parents=True, exist_ok=True)
    (job / "job.json").write_text(json.dumps(opts.to_json(), indent=2))
    results = {}
    for stage in stages:
        results[stage], skipped = run_stage(job, stage, opts, ctx)
        log.info("stage %s %s", stage, "skipped (marker matches)" if skipped else "done")
    return results


def first_unfinished(job: str | Path, opts: JobOptions) -> str | None:
    """The stage a retry would start from (None when all are done)."""
    for stage in STAGES:
        m = read_marker(job, stage)
        if m is None or m.get("config_hash") != config_hash(stage_config(opts, stage)):
            return stage
    return None
