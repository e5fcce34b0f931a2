"""The train stage: the mode probe (``--mode auto``), the resolved config (``pipeline.train.resolve``, saved as
``train/config.json``), and training with the collapse check."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.config import TrainConfig, to_dict
from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobCancelled, JobOptions, StageContext
from pipeline.scene.loader import load_scene
from pipeline.scene.records import scaled_view
from pipeline.scene.split import split_views
from pipeline.train import guard
from pipeline.train.hooks import curve_subset
from pipeline.train.photo_exposure import job_photo_exposure
from pipeline.train.probe import select_for_job
from pipeline.train.resolve import resolve_train_config, training_downscale
from pipeline.train.schedule import RULE, Schedule, coarse_iterations, iterations_factor
from pipeline.train.setup import load_training_images
from pipeline.train.trainer import TrainingCancelled
from pipeline.water.controller import medium_start_iteration


def stage_train(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    layout = JobLayout(job)
    scene = load_scene(layout.scene)
    train_views, test_views = split_views(scene.views)
    train_scene = scene.subset(train_views)
    # the classify stage's decision; in a folder from before its rename, the legacy file (JobLayout.legacy_classify)
    water = json.loads(found.read_text()) if (found := layout.classify_written) is not None else None
    # the images at the training size, read one at a time
    down = training_downscale(opts, scene.views[0].camera.width)
    images = load_training_images(train_scene.views, down, opts.colour_space)
    selection = None
    if opts.mode == "auto":  # the probe starts from the config resolved before its choice, at its views' width
        base = resolve_train_config(opts, train_scene.views[0].camera.width, water, None, len(scene.views))
        selection = select_mode(job, base, train_scene, images, water, ctx)
    cfg = resolve_train_config(opts, scene.views[0].camera.width, water, selection, len(scene.views))
    atomic_write_json(layout.train_config, to_dict(cfg))
    start = PROBE_SHARE if selection is not None else 0.0
    curve_views = [test_views[i] for i in curve_subset(len(test_views))]  # a few views keep the curve cheap
    test_images = load_training_images(curve_views, down, opts.colour_space)

    def progress(it: int, total: int, metrics: dict) -> None:
        ctx.on_progress("train", start + (1 - start) * it / max(1, total), f"iteration {it}/{total}")

    try:
        # through the module: tests/job/test_layout.py replaces guard.train_checked to see what training gets
        res, quality, recovery = guard.train_checked(train_scene, images, cfg, layout.train,
                                                     test_views=curve_views, test_images=test_images,
                                                     on_progress=progress, should_cancel=ctx.should_cancel,
                                                     device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(str(e)) from e
    exposure = res.exposure
    if exposure is not None:  # every photo's exposure, measured once against the trained model
        exposure = job_photo_exposure(job, [scaled_view(v, cfg.downscale) for v in scene.views], exposure,
                                      cfg.backend)
    out = {"mode": cfg.mode, "iterations": res.iteration, "metrics": res.metrics, "history": res.history,
           "medium": res.medium, "exposure": exposure,
           "elapsed_s": res.elapsed_s, "n_gaussians": int(res.gaussians["means"].shape[0]),
           "n_train_views": len(train_views), "n_test_views": len(test_views), "downscale": cfg.downscale,
           "curve_views": [v.name for v in curve_views], "quality": quality, "recovery": recovery,
           "schedule": job_schedule(cfg, len(scene.views), train_scene, opts.iterations is not None)}
    atomic_write_json(layout.train_result, out)
    return out


def job_schedule(cfg: TrainConfig, views: int, train_scene, explicit: bool) -> dict:
    """The schedule block of train_result.json and report.json (``pipeline.train.schedule.Schedule``)."""
    cam = scaled_view(train_scene.views[0], cfg.downscale).camera
    n = len(train_scene.views)
    d = cfg.densify  # resolved: in a medium mode its refine_stop is already the later one (medium_densify)
    medium = cfg.mode != "3dgs"
    medium_start = medium_start_iteration(cfg.iterations, cfg.medium.start_fraction) if medium else None
    coarse = coarse_iterations(cfg.iterations, cfg.coarse_fraction, medium_start)
    small = scaled_view(scaled_view(train_scene.views[0], cfg.downscale), cfg.coarse_downscale).camera
    return Schedule(views=views, train_views=n, width=cam.width, height=cam.height, pixels=n * cam.width * cam.height,
                    rule=RULE, factor=round(iterations_factor(views), 4), iterations=cfg.iterations,
                    explicit_iterations=explicit, passes=round(cfg.iterations / max(1, n), 2),
                    refine_every=d.refine_every, refine_start=d.refine_start, refine_stop=d.refine_stop,
                    reset_every=d.reset_every, max_gaussians=d.max_gaussians,
                    medium_start=medium_start, coarse_until=coarse, coarse_width=small.width if coarse else 0,
                    coarse_height=small.height if coarse else 0).to_json()


PROBE_SHARE = 0.1  # of the train stage's progress that the mode probe reports (mode auto)


def select_mode(job: Path, base: TrainConfig, scene, images, water: dict | None, ctx: StageContext) -> dict:
    """``--mode auto``: the probe on the training views (``pipeline.train.probe``) -> ``JobLayout.selection``.
    ``base`` is the job's config resolved before the choice (``resolve_train_config`` without a selection):
    the probe's runs take their seed, backend and medium settings (the water decision) from it."""
    try:
        return select_for_job(JobLayout(job).train, scene, images, base, water=water,
                              on_progress=lambda f, m: ctx.on_progress("train", PROBE_SHARE * f, m),
                              should_cancel=ctx.should_cancel, device=ctx.device)
    except TrainingCancelled as e:
        raise JobCancelled(f"cancelled during the mode probe: {e}") from e
