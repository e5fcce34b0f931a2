"""The restore stage: every registered input photo de-watered at its own resolution and in its own lens
geometry -> ``JobLayout.restored`` and ``JobLayout.confidence``, with what happened per photo in
``JobLayout.restore_result``."""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json, read_marker
from pipeline.job.options import JobCancelled, JobOptions, StageContext
from pipeline.restore.consistency import restored_consistency
from pipeline.restore.truth import score_restored
from pipeline.restore.views import NOTHING_TO_RESTORE, JobPhotos, restore_photo
from pipeline.scene.images import list_images
from pipeline.synth.ground_truth import find_ground_truth
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import model_from_state, training_views
from pipeline.train.render import displayed

log = logging.getLogger(__name__)


def stage_restore(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """One photo at a time (a frame is restored in row bands: bounded memory at any size); cancellable between
    photos. A photo SfM did not register has no pose and is listed as not restored. Every job's restored photos
    are scored without truth, by how well the same seabed keeps its colour across distances
    (:mod:`pipeline.restore.consistency`); with ground truth (a generated scene) also against the truth at full
    resolution (:mod:`pipeline.restore.truth`)."""
    layout = JobLayout(job)
    for folder in (layout.restored, layout.confidence):  # a re-run never mixes old and new photos
        shutil.rmtree(folder, ignore_errors=True)
    state = load_checkpoint(layout.checkpoint)
    model = model_from_state(state)
    if model.medium is None:
        res = {"mode": model.mode, "restored": 0, "note": NOTHING_TO_RESTORE, "views": []}
        atomic_write_json(layout.restore_result, res)
        return res
    views = training_views(job, state)
    job_photos = JobPhotos.of(job, model)
    lenses = job_photos.lenses
    photos = {p.name for p in list_images(layout.images)}
    gt = find_ground_truth(opts.source, opts.ground_truth)
    renders = {}  # with ground truth: each view's J as displayed, scored against the truth below
    per_view, t_all = [], time.perf_counter()
    for k, view in enumerate(views):
        if ctx.should_cancel():
            raise JobCancelled(f"cancelled during restore after {k} of {len(views)} photos")
        t0 = time.perf_counter()
        src = layout.images / view.name
        rendered, out, pad = job_photos.render(view)  # out to the photo's edges
        if gt is not None:  # the training camera's render, as restored/ held it before
            J = displayed(out, model.colour_space).J
            renders[view.name] = J[pad:J.shape[0] - pad, pad:J.shape[1] - pad]
        stats = restore_photo(src, layout.restored, layout.confidence, lenses[view.name], rendered,
                              max_gain=opts.max_gain, fmt=opts.restore_format, space=model.colour_space)
        per_view.append({"name": view.name, **stats, "seconds": round(time.perf_counter() - t0, 3)})
        ctx.on_progress("restore", (k + 1) / len(views), f"restored {k + 1}/{len(views)} photos")
    registered = {v.name for v in views}
    split = _split_models(job)
    res = {"mode": model.mode, "restored": len(per_view), "max_gain": opts.max_gain, "colour_space": model.colour_space,
           "format": opts.restore_format, "fall_off": job_photos.fall_record,
           "seconds": round(time.perf_counter() - t_all, 3), "views": per_view,
           "not_restored": [{"name": n, "reason": split.get(n, "SfM did not register it (no pose)")}
                            for n in sorted(photos - registered)]}
    res["consistency"] = restored_consistency(job, {v["name"]: v["file"] for v in per_view})  # no truth needed
    if gt is not None:
        res["truth"] = score_restored(job, gt, views, lenses, {v["name"]: v["file"] for v in per_view}, renders)
    atomic_write_json(layout.restore_result, res)
    log.info("restored %d photos in %.1f s", len(per_view), res["seconds"])
    return res


def _split_models(job: Path) -> dict[str, str]:
    """Image name → why it has no pose, for the images SfM placed in a model other than the one trained (a survey
    that broke into several models: ``SfmSummary.other_models``)."""
    result = ((read_marker(job, "sfm") or {}).get("result") or {})
    return {name: f"in SfM's separate model {m['index']} ({m['registered']} images); only the largest model was "
                  f"reconstructed" for m in result.get("other_models") or [] for name in m.get("images", [])}
