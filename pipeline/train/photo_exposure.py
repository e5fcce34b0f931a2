"""Every photo's exposure and white balance measured once, after training, from the trained model.

Training compares each view's photo at neutral exposure with gains the sparse points' water fit measured
(:mod:`pipeline.medium.exposure_fit`; learned in ``3dgs``). Those gains carry the fit's misfit between near and far
views, 1-2 % per view, and 1 % of gain costs about 0.5 dB of a restoration at 36 dB. The trained model is a better
reference than the sparse points: it predicts every pixel with the water included, and a gain multiplies every pixel
of a photo alike while a Gaussian's colour is shared by the views that see it. So each photo's gains are measured
again here, densely: the median over the pixels the model covers of log(photo / render) in linear light, per
channel, with the render at the gains training used. Held-out photos, which training never saw, are measured the
same way, from the render at neutral exposure.

The model sits at the training views' mean exposure; the correction's mean over the training views is what the
model gets wrong everywhere (not exposure) and is taken off every photo's, held-out ones too. A job whose sparse
points showed no exposure change between frames (:data:`~pipeline.medium.exposure_fit.EXPOSURE_EVIDENCE`) keeps
gains of 1 for every photo: a fixed camera's per-view residuals are the model's misfit, not exposure.

The train stage writes the result into train_result.json's ``exposure`` block (``photos``), and evaluation,
restoration and ``dualphys render`` read it from there (:func:`photo_gains`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.job.layout import JobLayout
from pipeline.medium.fall_off import as_photographed
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.loader import load_view_image
from pipeline.scene.records import View
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import TrainedModel, model_from_state
from pipeline.train.render import displayed, render_outputs

log = logging.getLogger(__name__)

COVERED = 0.95  # a pixel the model covers at least this much measures the gains
DARK, BRIGHT = 0.01, 0.98  # linear light: pixels darker (rendered or seen) or brighter carry no gain information
MIN_PIXELS = 500  # a photo's gains are measured from at least this many usable pixels per channel; else kept


def render_log_ratio(model: TrainedModel, view: View, photo: np.ndarray, log_gain: np.ndarray | None,
                     backend: str = "auto", fall_off: np.ndarray | None = None) -> np.ndarray | None:
    """:func:`log_ratio` of ``photo`` [H, W, 3] (sRGB in [0, 1], at the view's size) to the model rendered for
    ``view`` with its water."""
    out = displayed(render_outputs(model.gaussians, view, model.medium, model.sh_degree, backend, model.background),
                    model.colour_space)
    return log_ratio(out.I, out.alpha, photo, log_gain, fall_off)


def log_ratio(render: np.ndarray, alpha: np.ndarray, photo: np.ndarray, log_gain: np.ndarray | None,
              fall_off: np.ndarray | None = None) -> np.ndarray | None:
    """Per channel, the median over the covered, usable pixels of log(photo / render) in linear light, with the
    render (sRGB [H, W, 3], at neutral exposure) taken to exposure ``log_gain`` [3] (None: neutral) and the
    survey's fall-off (:func:`pipeline.medium.fall_off.as_photographed`); None where too few pixels are usable."""
    render = as_photographed(render, log_gain, fall_off)
    seen = srgb_to_linear(np.clip(np.asarray(photo, np.float64), 0, 1))
    pred = srgb_to_linear(np.clip(np.asarray(render, np.float64), 0, 1))
    covered = np.asarray(alpha) >= COVERED
    res = np.zeros(3)
    for c in range(3):
        ok = covered & (seen[..., c] > DARK) & (pred[..., c] > DARK) & (seen[..., c] < BRIGHT) & (pred[..., c] < BRIGHT)
        if int(ok.sum()) < MIN_PIXELS:
            return None
        res[c] = float(np.median(np.log(seen[..., c][ok] / pred[..., c][ok])))
    return res


def measure_photo_exposure(model: TrainedModel, views: Sequence[View], photos: Iterable[np.ndarray],
                           trained: dict[str, np.ndarray], backend: str = "auto", fall_off: np.ndarray | None = None
                           ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Every view's log gains [3] (linear light, on the model's exposure) measured against the model (module
    docstring): ``trained`` maps the training views' names to the log gains training used; the other ``views``
    are held out; ``fall_off``: the survey's fall-off training divided out (put back on the render). Returns
    (name → log gains, what was measured: the corrections' size and the views kept as they were)."""
    corr: dict[str, np.ndarray] = {}
    for v, photo in zip(views, photos, strict=True):
        r = render_log_ratio(model, v, photo, trained.get(v.name), backend, fall_off)
        if r is not None:
            corr[v.name] = r
    known = [corr[n] for n in trained if n in corr]
    offset = np.mean(known, axis=0) if known else np.zeros(3)  # the model's error everywhere, not exposure
    gains, kept = {}, []
    for v in views:
        base = trained.get(v.name, np.zeros(3))
        if v.name in corr:
            gains[v.name] = base + corr[v.name] - offset
        else:
            gains[v.name] = base
            kept.append(v.name)
    moved = [float(np.abs(corr[n] - offset).max()) for n in trained if n in corr]
    info = {"method": "dense: the trained model's render against each photo, median over covered pixels",
            "offset": [round(float(x), 4) for x in np.expm1(offset)],
            "max_correction": round(float(np.expm1(max(moved))) if moved else 0.0, 4),
            "not_measured": kept}
    if kept:
        log.warning("exposure of %d photos could not be measured against the model (fewer than %d covered, usable "
                    "pixels): %s keep %s", len(kept), MIN_PIXELS, ", ".join(kept[:5]),
                    "the gains training used" if any(n in trained for n in kept) else "neutral exposure")
    log.info("exposure measured against the trained model for %d photos: training views moved by up to %.1f %% from "
             "the gains training used", len(gains), 100 * info["max_correction"])
    return gains, info


def job_photo_exposure(job: Path, views: Sequence[View], record: dict[str, Any], backend: str = "auto"
                       ) -> dict[str, Any]:
    """train_result.json's ``exposure`` block (``record``: the training views' gains, :func:`~pipeline.train
    .exposure.exposure_record`) with every photo of ``views`` (the job's cameras at the training size) measured
    against the model in the job's checkpoint: ``photos`` (name → gains) and ``measured`` (how). A job whose points
    showed no change between frames gets gains of 1 for every photo."""
    if str(record.get("source", "")).startswith("none"):
        return {**record, "photos": {v.name: [1.0, 1.0, 1.0] for v in views},
                "measured": {"method": "none: the sparse points showed no change between frames"}}
    model = model_from_state(load_checkpoint(JobLayout(job).checkpoint))
    trained = {n: np.log(np.asarray(g, dtype=np.float64)) for n, g in record["views"].items()}
    gains, info = measure_photo_exposure(model, views, (load_view_image(v) for v in views), trained, backend,
                                         removed_fall_off(record))
    return {**record, "photos": {n: [round(float(x), 4) for x in np.exp(g)] for n, g in gains.items()},
            "measured": info}


def photo_gains(job: Path) -> dict[str, np.ndarray]:
    """Image name → log gains [3] (linear light, on the model's exposure) for every photo whose exposure the train
    stage measured (train_result.json's ``exposure.photos``; a job from before that: the training views' gains);
    empty when the job did not model exposure or the photos did not change it."""
    layout = JobLayout(job)
    if not layout.train_result.exists():
        return {}
    record = json.loads(layout.train_result.read_text()).get("exposure") or {}
    views = record.get("photos") or record.get("views") or {}
    gains = {name: np.log(np.asarray(g, dtype=np.float64)) for name, g in views.items()}
    return gains if any(np.any(g) for g in gains.values()) else {}


def removed_fall_off(record: dict[str, Any] | None) -> np.ndarray | None:
    """The survey's in-frame fall-off that training divided out of the photos, from train_result.json's
    ``exposure`` block (``record``; :func:`pipeline.medium.fall_off.fall_off_to_remove`): the log field's
    coefficients [5], or None when none was (the model then holds the photos' light as it was)."""
    fall = (record or {}).get("fall_off") or {}
    return np.asarray(fall["log_field"], np.float64) if fall.get("removed") else None


def photo_fall_off(job: Path) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """:func:`removed_fall_off` of a job's train_result.json, with the decision's record (None: not decided)."""
    layout = JobLayout(job)
    if not layout.train_result.exists():
        return None, None
    record = json.loads(layout.train_result.read_text()).get("exposure") or {}
    return removed_fall_off(record), record.get("fall_off")


def survey_exposure(gains: dict[str, np.ndarray]) -> np.ndarray | None:
    """The survey's mean exposure, log gains [3] on the model's (which is the training views' mean): the mean over
    every photo of :func:`photo_gains`. The restored photos are given it, so they sit at the mean of all the photos,
    not of the ones training happened to use; None without gains."""
    return np.mean(list(gains.values()), axis=0) if gains else None


__all__ = ["job_photo_exposure", "log_ratio", "measure_photo_exposure", "photo_fall_off",
           "photo_gains", "removed_fall_off", "render_log_ratio", "survey_exposure"]
