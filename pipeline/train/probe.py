"""Model only what a scene needs (``--mode auto``): a short probe on the training views picks the mode.

The probe never sees the test views of :func:`pipeline.scene.split.split_views`. It holds back the quarter of
the *training* views that see the scene from furthest away (median range to the sparse points), shrinks the
images to at most ``max_width`` pixels, runs one shared warm-up of plain splatting, then trains each candidate
mode briefly from that warm-up state and scores it on the held-back views, on the pixels every mode covers:

- ``psnr``: PSNR of the predicted photo (with the water, in medium modes) against the held-back images;
- ``effect`` (medium modes): how much the learned water changes those views, the mean over covered pixels and
  channels of ``(1 − A) + B`` (light the water removes plus light it adds), 0 for no water at all.

Every mode runs at SH degree 0, so the modes differ only in the water: with view-independent colour, plain
splatting cannot fake the colour change with range that water causes, and far views are where that change is
largest. Before any training, the photos' own drift with range at the sparse points (:func:`survey_drift`) says
whether there is water to model at all. The rule is :func:`decide`; its thresholds and the measurements behind
them are in docs/DECISIONS.md ("Automatic mode").
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.config import TrainConfig, rescheduled, to_dict
from pipeline.job.layout import SELECTION_NAME
from pipeline.job.markers import atomic_write_json, config_hash
from pipeline.medium.drift import photo_drift
from pipeline.medium.estimate import MediumEstimate, gather_observations
from pipeline.medium.measure import measure_observed
from pipeline.ops.metrics import pooled_psnr
from pipeline.scene.colour import linear_to_srgb
from pipeline.scene.exposure import neutral
from pipeline.scene.records import Scene, View, scaled_view, view_ranges
from pipeline.train.budget import scene_budget
from pipeline.train.quality import box_mean
from pipeline.train.setup import prepare_images
from pipeline.train.targets import take
from pipeline.train.trainer import Trainer, TrainingCancelled

log = logging.getLogger(__name__)

MODES: tuple[str, ...] = ("3dgs", "homogeneous", "dualphys")  # simplest first
FALL_OFF_CONFOUNDS = 1.3  # an in-frame fall-off (brightest / darkest) from which the sparse points' water is not a
#  measurement of how much water there is (measurement_kind). Measured: generated scenes without one 1.00-1.04,
#  with a 1.72x one 1.67; real sets AIMS Ugar 1.45-1.49, Erub 1.75-1.86, RUIE B571 1.31-1.37, A188 4.35 (lamps: its
#  photos' mean image falls ~4.8x from left to right), where the water measured beside it fell from 0.21 to 0.13
UNMEASURED = frozenset({"failed", "confounded"})  # the points' fit said nothing about how much water there is
ProbeProgress = Callable[[float, str], None]  # (fraction of the probe done, message)


@dataclass
class ProbeConfig:
    """The probe's size and the decision rule's thresholds (see docs/DECISIONS.md, "Automatic mode")."""

    min_views: int = 6  # fewer training views than this: no probe, plain 3dgs (nothing to hold back)
    holdout_fraction: float = 0.25  # this share of the training views, the furthest from the scene, is held back
    max_width: int = 128  # probe images are area-downscaled by an integer factor to at most this width
    warmup: int = 150  # shared plain-splatting iterations before the modes branch
    iterations: int = 250  # iterations of each mode after the warm-up (medium on from the first)
    max_gaussians: int = 20_000  # densification cap during the probe
    margin_db: float = 0.3  # homogeneous wins over dualphys when its held-back PSNR is within this of dualphys's
    noise_db: float = 0.3  # the probe's run-to-run spread: a medium that learned water is refused only when it
    #                        predicts the held-back views worse than plain splatting by more than this
    min_effect: float = 0.1  # learned water ((1 − A) + B on the held-back views) below this counts as none
    lr_reference_iterations: int = 2_000  # the medium's rate boost as for a run with this many medium steps
    min_alpha: float = 0.95  # held-back pixels are scored where every mode's Gaussians cover at least this much
    # ... unless that leaves under ``min_covered`` of them (far held-back views a short probe barely reaches:
    # the procedural survey's forward pass had 0 % at 0.95, 12-19 % at 0.5); then where every mode covers at least
    # ``relaxed_alpha``. Under ``min_covered`` even then, the race is inconclusive and :func:`decide` rests on the
    # water the sparse points measured.
    min_covered: float = 0.05
    relaxed_alpha: float = 0.5
    sh_degree: int = 0  # view-independent colour in every mode, so plain splatting cannot fake range-dependent colour
    window: int = 9  # the race compares local means over squares this wide (of a <= max_width image): water changes
    #                  a region's mean colour, a lens's blur or texture averaged at range does not (docs/DECISIONS.md)
    no_water_drift: float = 0.16  # the photos' own drift with range (survey_drift, largest channel) below this: no
    #  water. Without water 0.003-0.12 (lens blur the most), with water 0.29-1.5 (docs/DECISIONS.md)
    min_measured_effect: float = 0.22  # water the points measured: below it (when they did measure it) a won race
    #  is not enough, at or above it a lost race is outranked. Generated scenes without water 0.10-0.20 (0.197 with
    #  a lens's defocus); real RUIE A188 0.25-0.27, B571 0.46-0.70; generated clear water 0.47 (docs/DECISIONS.md)


@dataclass
class ModeScore:
    """One mode's probe result on the held-back views."""

    psnr: float  # dB, with water
    seconds: float  # this mode's training after the warm-up, plus its scoring
    covered: float  # share of the held-back pixels scored (rendered by every mode)
    effect: float | None = None  # mean (1 − A) + B over covered pixels; None for 3dgs
    measured_effect: float | None = None  # the same for the water the sparse points measured before training, at
    #                                       their median range (pipeline.medium.estimate); None without a measurement
    attenuation: float | None = None  # mean 1 − A
    backscatter: float | None = None  # mean B
    coefficients: dict[str, Any] = field(default_factory=dict)  # the medium's global β_D, β_B, B∞
    measurement: str | None = None  # how the sparse points measured the water (:func:`measurement_kind`)

    def to_json(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in dataclasses.asdict(self).items()}


@dataclass
class Selection:
    """What ``--mode auto`` chose and why (``JobLayout.selection``; the report's ``selection``)."""

    requested: str
    chosen: str
    reason: str
    margin: dict[str, float]  # the rule's thresholds: margin_db, min_effect
    probe: dict[str, dict]  # per mode: ModeScore.to_json()
    probe_setup: dict[str, Any]  # views fitted / held back, resolution, iterations, warm-up seconds, total seconds
    water: dict[str, Any] | None = None  # the classifier's type and probabilities, when known
    drift: dict[str, Any] | None = None  # the photos' own drift with range (survey_drift)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def holdout_split(views: Sequence[View], points: np.ndarray, fraction: float) -> tuple[list[int], list[int]]:
    """Indices (fit, held back) into ``views``: the ``fraction`` of views that see the scene from furthest away
    (median range to the sparse points) are held back, at least one; at least two are fitted.

    Water is what changes a surface's colour with range, so predicting views further away than any fitted one
    is where a water model earns its keep and where a model that learned water that is not there loses. Without
    sparse points the views are held back by name (every 1/fraction-th).
    """
    if len(views) < 3:
        raise ValueError(f"the mode probe needs at least 3 training views, got {len(views)}")
    n_held = min(len(views) - 2, max(1, round(fraction * len(views))))
    ranges = view_ranges(points, views)
    if np.isnan(ranges).all():
        order = sorted(range(len(views)), key=lambda i: views[i].name)
        every = max(2, round(1 / fraction))
        held = [i for k, i in enumerate(order) if k % every == every // 2][:n_held]
    else:
        held = sorted(np.argsort(np.nan_to_num(ranges, nan=-np.inf))[::-1][:n_held].tolist())
    fit = [i for i in range(len(views)) if i not in held]
    return fit, held


def measurement_kind(estimate: dict | None) -> str | None:
    """How the sparse points measured the water, from a :class:`MediumEstimate` dict: ``failed`` (a channel's fit
    was not a measurement, the water type's prior stands in: ``pipeline.medium.estimate.fit_failure``),
    ``confounded`` (the photos' in-frame fall-off, measured beside the water, spans :data:`FALL_OFF_CONFOUNDS` or
    more: it shares the water's signal, a grey darkening towards the far side of an oblique frame, so a weak water
    measured beside it is no evidence of no water), ``measured`` (the data pinned β_D in every channel), ``prior``
    (the data could not: too little range spread); None without an estimate."""
    if not estimate:
        return None
    unc = estimate.get("uncertainty") or {}
    if any(unc.get("failed") or []):
        return "failed"
    if (estimate.get("field_span") or 1.0) >= FALL_OFF_CONFOUNDS:
        return "confounded"
    sources = (unc.get("beta_D") or {}).get("source") or []
    return "measured" if sources and all(x == "measured" for x in sources) else "prior"


def classified_water(water: dict | None) -> str | None:
    """The classifier's water type when it calls the water ``medium`` or ``turbid`` and knows what it sees (not
    ``known: false``: image statistics outside its training), else None."""
    if not water or water.get("known") is False:
        return None
    kind = water.get("water_type")
    return kind if kind in ("medium", "turbid") else None


def survey_drift(scene: Scene, images: Sequence[Any], base: TrainConfig) -> dict:
    """:func:`~pipeline.medium.drift.photo_drift` of the training views' photos (``images`` at the job's training
    size and colour space) at their sparse points, each photo at neutral exposure (the water fit's gains, the same
    fit training starts from), in sRGB as calibrated."""
    if not len(scene.points):
        return {"defined": False, "reason": "the scene has no sparse points", "score": None}
    views = [scaled_view(v, base.downscale) for v in scene.views]
    frames = [images[i] for i in range(len(views))]
    space = base.colour_space
    obs = gather_observations(scene.points, views, frames, scene.sightings)
    est = measure_observed(obs, len(views), base.medium.init_optical_depth, space if base.exposure != "off" else None)
    colour = obs.colour
    if est is not None and est.log_gains is not None and obs.view is not None:
        colour = neutral(colour, np.asarray(est.log_gains)[obs.view], space)
    if space == "linear":
        colour = linear_to_srgb(np.clip(colour, 0, 1))
    return photo_drift(dataclasses.replace(obs, colour=np.asarray(colour, np.float64)))


def decide(scores: dict[str, ModeScore], cfg: ProbeConfig, water: dict | None = None,
           drift: dict | None = None) -> tuple[str, str]:
    """(chosen mode, reason). First, photos whose colours do not drift with range (``drift``, :func:`survey_drift`,
    below ``no_water_drift``) have no water to model: ``3dgs``, whatever the race, the points' fit or the
    classifier say (on generated scenes without water, fitted on SfM poses, the points "measured" 0.29 of water
    and the medium won the race by 2.8 dB; restored, the photos lost 27 dB). Otherwise a water model is needed
    when both hold:

    - the medium modes learned water: the largest ``effect`` is at least ``min_effect``;
    - a medium mode predicts the held-back (furthest) views about as well as plain splatting or better: water
      that is really there explains how colours change with range, water that the model invented costs
      held-back PSNR. "About": within the probe's own run-to-run spread ``noise_db`` (measured on real and
      generated scenes, docs/DECISIONS.md); a margin below the noise would flip the mode between seeds and
      between overlapping subsets of the same site. Or, when that race is lost, the sparse points measured
      the water before training (``measured_effect`` >= ``min_measured_effect``): the race guards against invented
      water, and water measured from the points' colour change across ranges is not invented (on real hazy
      footage plain splatting won the far views by 1-4 dB while the points measured 0.46-0.66 of water).

    Water the medium barely learned in the probe (``effect`` < ``min_effect``) is still water when the classifier
    calls it ``medium`` or ``turbid`` (:func:`classified_water`) and the sparse points' fit failed
    (:func:`measurement_kind`); then only a race lost by more than ``noise_db`` gives ``3dgs``. Where the fit held
    (measured, or prior-dominated: the medium then starts from the water type's values and the probe's training
    is what shrank it), the learned water decides: the classifier has no "no water" class and calls generated
    scenes without water ``medium``.

    A race won while the sparse points did measure the water and found less than ``min_measured_effect`` is not
    water: with plain splatting trained on random backgrounds (so it cannot paint dark surfaces with the black
    background), a medium still won the held-back views of generated scenes without water by 1.3-3.9 dB, its veil
    pulling poorly fitted far colours to the mean; ``3dgs`` then.

    Then the simplest medium mode within ``margin_db`` of the best medium mode is chosen, else ``3dgs``.
    (Splatting can imitate water in the photos, so "3dgs is within the margin of the best" alone cannot show
    that a scene has no water worth modelling out; hence the asymmetric test against 3dgs.)"""
    detail = _race_detail(scores)
    if drift and drift.get("defined") and drift["score"] < cfg.no_water_drift:
        return "3dgs", (f"the photos show no water: between near and far sightings the same seabed point's colour "
                        f"changes by {drift['score']:.3f} of the seabed's contrast at most (< {cfg.no_water_drift:g};"
                        f" water makes it 0.29-1.5, lens blur without water up to 0.12; ranges "
                        f"{drift['range_ratio']:.2f}x): plain splatting. {detail}")
    media = {m: s for m, s in scores.items() if s.effect is not None}
    covered = max((s.covered for s in scores.values()), default=0.0)
    if covered < cfg.min_covered:  # nothing (or next to nothing) scored: no race to rest on
        return _decide_unscored(media, covered, cfg, water, detail)
    if not media:
        return "3dgs", f"no medium mode was probed. {detail}"
    return _decide_race(_Race.of(scores, media, cfg), media, cfg, water, detail)


def _race_detail(scores: dict[str, ModeScore]) -> str:
    """Every probed mode's held-back PSNR (and learned water), simplest first: the tail of each reason."""
    return "; ".join(f"{m} {scores[m].psnr:.2f} dB" + (f" (water {scores[m].effect:.3f})"
                                                      if scores[m].effect is not None else "")
                     for m in MODES if m in scores)


def _decide_unscored(media: dict[str, ModeScore], covered: float, cfg: ProbeConfig, water: dict | None,
                     detail: str) -> tuple[str, str]:
    """:func:`decide` when the fitted views cover under ``min_covered`` of the held-back pixels: no race to rest
    on, so the water the sparse points measured, or the classifier when their fit failed, decides."""
    measured = max((s.measured_effect or 0.0 for s in media.values()), default=0.0)
    where = (f"the fitted views' Gaussians cover only {100 * covered:.1f} % of the held-back pixels "
             f"(< {100 * cfg.min_covered:g} %), so the race between the modes is inconclusive")
    simplest = next((m for m in MODES if m in media), None)
    if simplest is not None and measured >= cfg.min_measured_effect:
        return simplest, (f"{where}; the sparse points measured water before training ({measured:.3f} >= "
                          f"{cfg.min_measured_effect:g}): the simplest medium mode. {detail}")
    typed = classified_water(water)
    if simplest is not None and typed is not None and any(s.measurement in UNMEASURED for s in media.values()):
        return simplest, (f"{where}; the classifier calls the water {typed} and the sparse points' fit failed: "
                          f"the simplest medium mode. {detail}")
    return "3dgs", (f"{where}, and the sparse points do not measure enough water ({measured:.3f} < "
                    f"{cfg.min_measured_effect:g}): the simplest mode. {detail}")


@dataclass(frozen=True)
class _Race:
    """What :func:`decide` reads of a scored race with at least one medium mode."""

    learned: float  # the largest water a medium mode learned (effect)
    measured: float  # the largest water the sparse points measured (measured_effect), 0 without a measurement
    plain: float  # 3dgs's held-back PSNR (-inf when it was not probed)
    best: float  # the best medium mode's held-back PSNR
    mode: str  # the simplest medium mode within margin_db of the best
    simplest: str  # how the reasons name ``mode``

    @classmethod
    def of(cls, scores: dict[str, ModeScore], media: dict[str, ModeScore], cfg: ProbeConfig) -> _Race:
        best_medium = max(media, key=lambda m: media[m].psnr)
        best = media[best_medium].psnr
        return cls(learned=max((s.effect or 0.0 for s in media.values()), default=0.0),
                   measured=max((s.measured_effect or 0.0 for s in media.values()), default=0.0),
                   plain=scores["3dgs"].psnr if "3dgs" in scores else -math.inf, best=best,
                   mode=next(m for m in MODES if m in media and media[m].psnr >= best - cfg.margin_db),
                   simplest=f"the simplest medium mode within {cfg.margin_db:g} dB of the best ({best_medium})")


def _decide_race(race: _Race, media: dict[str, ModeScore], cfg: ProbeConfig, water: dict | None,
                 detail: str) -> tuple[str, str]:
    """:func:`decide` on a scored race: learned water, the race against plain splatting, the points' measure."""
    learned, measured, plain, best, mode = race.learned, race.measured, race.plain, race.best, race.mode
    if learned < cfg.min_effect:
        return _decide_little_learned(race, media, cfg, water, detail)
    weak = {s.measurement for s in media.values()} == {"measured"} and measured < cfg.min_measured_effect
    if best >= plain - cfg.noise_db and weak:  # the points measured little water: the race is won by freedom
        return "3dgs", (f"the sparse points measured little water ({measured:.3f} < {cfg.min_measured_effect:g}); "
                        f"a medium's edge on the held-back views ({best - plain:+.2f} dB) is what its extra freedom "
                        f"buys on scenes without water too (generated: +1.3 to +3.9 dB at measured 0.10-0.20): "
                        f"plain splatting. {detail}")
    if best >= plain - cfg.noise_db:
        return mode, (f"the scene has water ({learned:.3f} >= {cfg.min_effect:g}) that predicts the held-back "
                      f"views as well as plain splatting (within the probe's noise, {cfg.noise_db:g} dB); "
                      f"{race.simplest}. {detail}")
    if measured >= cfg.min_measured_effect:
        return mode, (f"the scene has water: learned {learned:.3f} and measured from the sparse points before "
                      f"training {measured:.3f} (>= {cfg.min_measured_effect:g}); plain splatting predicts the "
                      f"held-back views {plain - best:.2f} dB better, which water the points measured cannot be "
                      f"blamed for (real footage: exposure changes, moving animals); {race.simplest}. {detail}")
    return "3dgs", (f"the learned water ({learned:.3f}) predicts the held-back views worse than plain "
                    f"splatting by more than the probe's noise ({best:.2f} < {plain:.2f} - {cfg.noise_db:g} dB) "
                    f"and the sparse points do not measure enough of it ({measured:.3f} < "
                    f"{cfg.min_measured_effect:g}). {detail}")


def _decide_little_learned(race: _Race, media: dict[str, ModeScore], cfg: ProbeConfig, water: dict | None,
                           detail: str) -> tuple[str, str]:
    """:func:`decide` when the medium learned under ``min_effect`` of water: still water when the classifier
    calls it medium or turbid and the sparse points' fit failed, unless the race is lost beyond the noise."""
    kinds = {s.measurement for s in media.values()}
    typed = classified_water(water)
    if typed is None or not kinds & UNMEASURED:
        return "3dgs", f"no water worth modelling (learned water {race.learned:.3f} < {cfg.min_effect:g}). {detail}"
    # the points could not measure it, the images show water
    probs = (water or {}).get("probabilities") or {}
    said = f"the classifier calls the water {typed} (p {probs.get(typed, float('nan')):.2f})"
    if race.best >= race.plain - cfg.noise_db:
        return race.mode, (f"{said}, the sparse points' fit failed (the report says why)"
                           f" and the medium learned little of it in the probe ({race.learned:.3f} < "
                           f"{cfg.min_effect:g}), but it predicts the held-back views as well as plain splatting "
                           f"(within the probe's noise, {cfg.noise_db:g} dB): a medium, not no water; "
                           f"{race.simplest}. {detail}")
    return "3dgs", (f"{said}, but the medium predicts the held-back views worse than plain splatting by more "
                    f"than the probe's noise ({race.best:.2f} < {race.plain:.2f} - {cfg.noise_db:g} dB) and "
                    f"learned little water ({race.learned:.3f}): plain splatting. {detail}")


def probe_config(base: TrainConfig, cfg: ProbeConfig, width: int, mode: str) -> TrainConfig:
    """``base`` (the job's resolved config, ``pipeline.train.resolve``) as a short run of ``mode`` in the probe's
    schedule: warm-up + iterations with the 30k schedule compressed to fit, the probe's Gaussian cap and SH
    degree, its image width, the medium (``base``'s, with the water decision) on right after the warm-up; no
    coarse start (the probe's images are small already), checkpoints, log lines or held-out evaluation."""
    total = cfg.warmup + cfg.iterations
    c = rescheduled(base, total, checkpoint_every=0, max_gaussians=cfg.max_gaussians)
    medium = dataclasses.replace(base.medium, start_fraction=cfg.warmup / total,
                                 lr_reference_iterations=cfg.lr_reference_iterations)
    return dataclasses.replace(c, mode=mode, log_every=0, eval_every=0, sh_degree=cfg.sh_degree,
                               downscale=max(1, math.ceil(width / cfg.max_width)), medium=medium,
                               coarse_fraction=0.0, random_background=mode == "3dgs")


def _render_held(trainer, views: Sequence[View]) -> list:
    """The trained probe model's outputs (I, A, B, alpha) for the held-back views."""
    return [trainer.outputs(v) for v in views]


def surface_colour(out) -> np.ndarray:
    """What a mode predicts for the surface at each pixel, whatever its coverage: the colour over alpha, with the
    water between (J·A + α·B) / α in medium modes, J / α in plain splatting. Scored this way, a pixel the fitted
    views half cover is no contest between plain splatting's black background and the medium's veil B∞ filling
    the rest (a generated scene without water, its far views scored at alpha 0.5: the medium won by 0.7-5 dB)."""
    a = np.maximum(np.asarray(out.alpha, np.float64), 1e-3)[..., None]
    if out.A is None or out.B is None:
        return np.clip(out.J / a, 0.0, 1.0)
    return np.clip((out.J * out.A + a * out.B) / a, 0.0, 1.0)


def _score(outputs: list, targets: Sequence[np.ndarray], masks: Sequence[np.ndarray], window: int = 1,
           photographed: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, float]:
    """PSNR with water of the predicted surface colour (:func:`surface_colour`) over the masked pixels of all
    held-back views (pooled) and, for a medium, its mean attenuation 1 − A and backscatter B there. With
    ``window`` > 1 the PSNR compares local means over
    ``window`` x ``window`` squares, on pixels whose whole square is masked (``ProbeConfig.window``).
    ``photographed``: the prediction as the camera recorded it (the survey's fall-off put back where the mode's
    training divided it out, :meth:`pipeline.train.exposure.ViewExposure.photographed`), so every mode is scored
    against the photos as they are."""
    att, bs = [], []
    for out, m in zip(outputs, masks, strict=True):
        if out.A is not None and out.B is not None:
            att.append(1.0 - out.A[m])
            bs.append(out.B[m])
    covered = sum(int(m.sum()) for m in masks)  # no pixel every mode covered: all modes tie at +inf
    as_taken = photographed or (lambda x: x)
    pairs = [(np.clip(as_taken(surface_colour(out)), 0.0, 1.0), t) for out, t in zip(outputs, targets, strict=True)]
    scored = list(masks)
    if window > 1:
        local = [(box_mean(a, window), box_mean(b, window)) for a, b in pairs]
        wide = [box_mean(m.astype(np.float64), window) > 1 - 1e-9 for m in masks]
        if sum(int(m.sum()) for m in wide):  # else no square wholly covered: score pixel by pixel
            pairs, scored = local, wide
    psnr = pooled_psnr(pairs, scored) if covered else math.inf
    res = {"psnr": psnr, "covered": covered / sum(m.size for m in masks)}
    if att:
        a, b = float(np.concatenate(att).mean()), float(np.concatenate(bs).mean())
        res.update(attenuation=a, backscatter=b, effect=a + b)
    return res


def common_cover(outputs: dict[str, list], modes: Sequence[str], min_alpha: float) -> list[np.ndarray]:
    """Per held-back view, the pixels every mode's Gaussians cover with alpha above ``min_alpha``."""
    n = len(outputs[modes[0]])
    return [np.logical_and.reduce([outputs[m][i].alpha > min_alpha for m in modes]) for i in range(n)]


def _share(masks: Sequence[np.ndarray]) -> float:
    return sum(int(m.sum()) for m in masks) / max(1, sum(m.size for m in masks))


def _steps(trainer, n: int, should_cancel: Callable[[], bool]) -> None:
    for _ in range(n):
        if should_cancel():
            raise TrainingCancelled(trainer.iteration)
        trainer.step()


def run_probe(scene: Scene, images: Sequence[Any], base: TrainConfig, cfg: ProbeConfig | None = None, *,
              modes: Sequence[str] = MODES, requested: str = "auto", water: dict | None = None,
              on_progress: ProbeProgress | None = None, should_cancel: Callable[[], bool] = lambda: False,
              device: str = "cpu") -> Selection:
    """Probe ``modes`` on the training views of ``scene`` (``images[i]`` belongs to ``scene.views[i]``) and
    decide. ``base`` supplies the seed, backend and medium settings (the water decision applied)."""
    cfg = cfg or ProbeConfig()
    report = on_progress or (lambda f, m: None)
    t_start = time.perf_counter()
    drift = survey_drift(scene, images, base)
    log.info("the photos' drift with range: %s", f"{drift['score']:.3f} (largest channel)" if drift.get("defined")
             else f"undefined ({drift['reason']})")
    fit, held = holdout_split(scene.views, scene.points, cfg.holdout_fraction)
    width = scene.views[0].camera.width
    fit_scene = scene.subset([scene.views[i] for i in fit])  # keeps the points' tracks
    fit_images = take(images, fit)  # packed images stay packed
    cfg3 = probe_config(base, cfg, width, "3dgs")
    held_views, held_targets = prepare_images([scene.views[i] for i in held], take(images, held),
                                              cfg3.downscale, torch.device(device))
    total_steps = cfg.warmup + cfg.iterations * len(modes)
    report(0.0, f"probe: warm-up on {len(fit)} views, {len(held)} held back")
    t0 = time.perf_counter()
    warm = Trainer(fit_scene, fit_images, cfg3, device=device)
    _steps(warm, cfg.warmup, should_cancel)
    warm_state = warm.state_dict()
    warm_s = time.perf_counter() - t0
    outputs, seconds, coefficients, measured, kinds, photographed = {}, {}, {}, {}, {}, {}
    for k, mode in enumerate(modes):
        report((cfg.warmup + k * cfg.iterations) / total_steps, f"probe: {mode}")
        t0 = time.perf_counter()
        mcfg = probe_config(base, cfg, width, mode)
        tr = Trainer(fit_scene, fit_images, mcfg, device=device)
        state = copy.deepcopy(warm_state)  # branches must not share tensors (Adam updates in place)
        state.update(mode=mode, config=to_dict(mcfg), medium=None)
        tr.load_state_dict(state)
        _steps(tr, cfg.iterations, should_cancel)
        outputs[mode] = _render_held(tr, held_views)
        photographed[mode] = tr.exposure.photographed if tr.exposure is not None else None
        seconds[mode] = time.perf_counter() - t0
        if tr.medium is not None:
            coefficients[mode] = {k: v for k, v in tr.medium.effective_coefficients().items() if k != "units"}
            if tr.medium.estimate is not None:
                measured[mode] = MediumEstimate(**tr.medium.estimate).effect()
                kinds[mode] = measurement_kind(tr.medium.estimate)
    # Score only where every mode rendered a surface: where the fitted views never reached, the medium modes
    # would win by painting the water's colour and plain splatting lose by painting black.
    targets = [t.cpu().numpy() for t in held_targets]
    scored_alpha = cfg.min_alpha
    masks = common_cover(outputs, modes, scored_alpha)
    if _share(masks) < cfg.min_covered:
        scored_alpha = cfg.relaxed_alpha
        masks = common_cover(outputs, modes, scored_alpha)
    scores: dict[str, ModeScore] = {}
    for mode in modes:
        s = _score(outputs[mode], targets, masks, cfg.window, photographed[mode])
        scores[mode] = ModeScore(seconds=seconds[mode], coefficients=coefficients.get(mode, {}),
                                 measured_effect=measured.get(mode), measurement=kinds.get(mode), **s)
        log.info("probe %s: held-back PSNR %.2f dB%s (%.1f s)", mode, s["psnr"],
                 f", water effect {s['effect']:.3f}" if "effect" in s else "", seconds[mode])
    chosen, reason = decide(scores, cfg, water, drift)
    report(1.0, f"probe: chose {chosen}")
    cam = held_views[0].camera
    setup = {"fit_views": [scene.views[i].name for i in fit], "held_back_views": [scene.views[i].name for i in held],
             "resolution": [cam.width, cam.height], "warmup_iterations": cfg.warmup,
             "iterations_per_mode": cfg.iterations, "sh_degree": cfg.sh_degree, "warmup_seconds": round(warm_s, 2),
             "scored_alpha": scored_alpha,
             "seconds": round(time.perf_counter() - t_start, 2)}
    log.info("mode auto: %s (%s)", chosen, reason)
    return Selection(requested=requested, chosen=chosen, reason=reason,
                     margin=_margins(cfg),
                     probe={m: s.to_json() for m, s in scores.items()}, probe_setup=setup,
                     water=_water_summary(water), drift=drift)


def _margins(cfg: ProbeConfig) -> dict[str, float]:
    return {"margin_db": cfg.margin_db, "min_effect": cfg.min_effect, "noise_db": cfg.noise_db,
            "min_measured_effect": cfg.min_measured_effect, "window": cfg.window, "no_water_drift": cfg.no_water_drift}


def _water_summary(water: dict | None) -> dict | None:
    keys = ("water_type", "probabilities", "closest", "known", "confidence")
    return {k: water[k] for k in keys if k in water} if water else None


def select_for_job(out_dir: Path, scene: Scene, images: Sequence[Any], base: TrainConfig, *,
                   water: dict | None = None, cfg: ProbeConfig | None = None,
                   on_progress: ProbeProgress | None = None, should_cancel: Callable[[], bool] = lambda: False,
                   device: str = "cpu") -> dict:
    """``--mode auto`` in a job: probe, decide, scale the budget to the scene, write ``out_dir/selection.json``
    and return its content. A selection.json written for the same inputs is reused (a resumed training job
    does not probe again)."""
    cfg = cfg or ProbeConfig()
    key = config_hash({"base": to_dict(base), "probe": dataclasses.asdict(cfg),
                       "views": [v.name for v in scene.views], "water": water})
    path = Path(out_dir) / SELECTION_FILE
    if path.exists():
        saved = json.loads(path.read_text())
        if saved.get("key") == key:
            log.info("mode auto: reusing %s (%s)", path, saved["chosen"])
            return saved
    if len(scene.views) < cfg.min_views:
        sel = Selection(requested="auto", chosen="3dgs",
                        margin=_margins(cfg),
                        reason=f"{len(scene.views)} training views are too few to hold some back for the probe "
                               f"(it needs {cfg.min_views}); the simplest mode", probe={},
                        probe_setup={"skipped": True}, water=_water_summary(water))
    else:
        sel = run_probe(scene, images, base, cfg, water=water, on_progress=on_progress,
                        should_cancel=should_cancel, device=device)
    cam = scene.views[0].camera
    budget = scene_budget(len(scene.views), cam.width // base.downscale, cam.height // base.downscale,
                          base.densify.max_gaussians, base.sh_degree)
    out = {**sel.to_json(), "budget": budget.to_json(), "key": key}
    atomic_write_json(path, out)
    return json.loads(path.read_text())  # exactly what a resumed job and the report will read


SELECTION_FILE = SELECTION_NAME  # in the train folder (a job's JobLayout.selection)

__all__ = ["MODES", "ModeScore", "ProbeConfig", "Selection", "classified_water", "common_cover", "decide",
           "holdout_split", "measurement_kind", "probe_config", "run_probe", "select_for_job", "SELECTION_FILE"]
