"""The train stage: the mode probe (``--mode auto``), the config, and training with the collapse check."""

from __future__ import annotations

import json
import math
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobCancelled, JobOptions, StageContext


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
    from pipeline.config import train_preset

    cfg = train_preset(opts.preset)
    if opts.iterations is not None:
        from pipeline.config import scaled_train_config

        cfg = scaled_train_config(opts.iterations, checkpoint_every=max(1, opts.iterations // 5),
                                  max_gaussians=300_000)
    cfg.seed = opts.seed
    cfg.mode = mode or opts.mode  # type: ignore[assignment]
    if cfg.mode == "auto":
        raise ValueError("train_config: mode 'auto' must be resolved first (pipeline.train.probe)")
    cfg.downscale = max(1, math.ceil(width / opts.max_width))
    from pipeline.train.hooks import curve_every

    cfg.eval_every = curve_every(cfg.iterations)  # the speed-vs-error curve's fixed schedule
    return cfg


def stage_train(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from pipeline.job.markers import atomic_write_json
    from pipeline.scene.loader import load_images, load_scene
    from pipeline.scene.split import split_views
    from pipeline.train.guard import train_checked
    from pipeline.train.trainer import TrainingCancelled

    layout = JobLayout(job)
    scene = load_scene(layout.scene)
    train_views, test_views = split_views(scene.views)
    train_scene = scene.subset(train_views)
    images = load_images(train_scene)
    # the classify stage's decision; in a folder from before its rename, the legacy file (JobLayout.legacy_classify)
    water = json.loads(found.read_text()) if (found := layout.classify_written) is not None else None
    selection = select_mode(job, opts, train_scene, images, water, ctx) if opts.mode == "auto" else None
    cfg = train_config(opts, scene.views[0].camera.width, selection["chosen"] if selection else None)
    if selection is not None:  # the Gaussian budget and SH degree scaled to the scene (pipeline.train.budget)
        cfg.sh_degree = selection["budget"]["sh_degree"]
        cfg.densify.max_gaussians = selection["budget"]["max_gaussians"]
    if cfg.mode != "3dgs" and water is not None:
        apply_water_decision(cfg, water)
    start = PROBE_SHARE if selection is not None else 0.0
    from pipeline.train.hooks import curve_subset

    curve_views = [test_views[i] for i in curve_subset(len(test_views))]  # a few views keep the curve cheap
    test_images = load_images(type(scene)(curve_views, root=scene.root)) if curve_views else []

    def progress(it: int, total: int, metrics: dict) -> None:
        ctx.on_progress("train", start + (1 - start) * it / max(1, total), f"iteration {it}/{total}")

    try:
        res, quality, recovery = train_checked(train_scene, images, cfg, layout.train, test_views=curve_views,
                                               test_images=test_images, on_progress=progress,
                                               should_cancel=ctx.should_cancel, device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(str(e)) from e
    out = {"mode": cfg.mode, "iterations": res.iteration, "metrics": res.metrics, "history": res.history,
           "medium": res.medium,
           "elapsed_s": res.elapsed_s, "n_gaussians": int(res.gaussians["means"].shape[0]),
           "n_train_views": len(train_views), "n_test_views": len(test_views), "downscale": cfg.downscale,
           "curve_views": [v.name for v in curve_views], "quality": quality, "recovery": recovery}
    atomic_write_json(layout.train_result, out)
    return out


PROBE_SHARE = 0.1  # of the train stage's progress that the mode probe reports (mode auto)


def select_mode(job: Path, opts: JobOptions, scene, images, water: dict | None, ctx: StageContext) -> dict:
    """``--mode auto``: the probe on the training views (``pipeline.train.probe``) -> ``JobLayout.selection``."""
    from pipeline.train.probe import select_for_job
    from pipeline.train.trainer import TrainingCancelled

    base = train_config(opts, scene.views[0].camera.width, "dualphys")  # seed, backend, caps, medium settings
    if water is not None:
        apply_water_decision(base, water)
    try:
        return select_for_job(JobLayout(job).train, scene, images, base, water=water,
                              on_progress=lambda f, m: ctx.on_progress("train", PROBE_SHARE * f, m),
                              should_cancel=ctx.should_cancel, device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(f"cancelled during the mode probe: {e}") from e
