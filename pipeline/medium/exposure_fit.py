"""The water fit with every view's exposure and white balance measured beside it.

A sighting of point p in view v is ``encode(g_v · L_p,v)`` where L_p,v is what a fixed camera would record through
the water (:mod:`pipeline.scene.exposure`). Left out, a frame-to-frame exposure change is a colour change the
water must explain, and on real video it did not (the RUIE fit put B∞ on its bound, :func:`~pipeline.medium.estimate
.fit_failure`). The fit alternates: the water from the sightings at neutral exposure and without the survey's
in-frame fall-off (:func:`~pipeline.medium.estimate.fit_medium`), then each view's gains and the fall-off from the
ratios, in linear light, of the sightings to what the water and the points' colours predict
(:func:`~pipeline.medium.exposure_gains.gains_beside_field`), mean-neutral.

The fall-off is taken out of the water's sightings too. Left in, it is a change of brightness with range wherever
range changes over the frame, and on AIMS Erub (brighter at the bottom of the frame, which is farther) the water
fit put green's and blue's veil on its bound; taken out, it measured every coefficient but blue's veil. The water
and the field then trade a little every round (Erub's β_D R 0.52, 0.59, 0.70 per unit after rounds 2, 5 and 12,
the misfit flat), so the rounds stay at 5; a generated scene with a known fall-off converges in ~15 rounds and is
within 22 % of its β_D after 5 (the fit before the fall-off: 127 % off).

What separates a gain from the water is range within a view: a gain multiplies every sighting of the view alike,
the water changes them with range. A view that sits farther away than the others as a whole is partly explained
by its gain; training refines both (:mod:`pipeline.train.exposure`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from pipeline.medium.estimate import MediumEstimate, Observations, fit_medium
from pipeline.medium.exposure_gains import FIELD_TERMS, field_span, field_values, gains_beside_field
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.exposure import mean_neutral, neutral

log = logging.getLogger(__name__)

ROUNDS = 5  # water fits, each followed by the gains' and the fall-off's update (why 5: the module docstring)
EXPOSURE_EVIDENCE = 25.0  # exposure_evidence above this: the frames' exposure changed; below, the gains are noise and
#  held at 1. Measured (with the fall-off): generated scenes of a fixed camera 6-10 (gains 1-2 % std, the water
#  model's misfit between near and far views), with ±30 % gains 2,900-7,300; real RUIE video 180 (A188) and
#  410-430 (B571), AIMS Erub 40-60 and Ugar 50 (gains ±4-7 %); a fixed camera with a fall-off of 1.7x 110-120
#  (gains within 2 %)
INNER = 10  # gain / point-colour alternations per round
DARK = 0.01  # linear light: sightings darker than this (predicted or seen) carry no exposure information


def _water(r: np.ndarray, est: MediumEstimate | None) -> tuple[np.ndarray, np.ndarray]:
    """The water's transmission e^(−β_D r) and veil B∞(1 − e^(−β_B r)) at ranges ``r`` [M]; None: no water (1 and
    0). ([M, 3], [M, 3])"""
    r = np.asarray(r, np.float64)[:, None]
    if est is None:
        return np.ones((len(r), 3)), np.zeros((len(r), 3))
    return np.exp(-np.asarray(est.beta_D) * r), np.asarray(est.B_inf) * (1 - np.exp(-np.asarray(est.beta_B) * r))


def _point_colours(point: np.ndarray, colour: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Each point's colour J [n, 3] solved in closed form from its sightings (least squares of J·a + b = colour,
    clamped to [0, 1]: the fit's variable projection)."""
    return np.clip(np.stack([np.bincount(point, a[:, c] * (colour[:, c] - b[:, c]), minlength=n)
                             / np.maximum(np.bincount(point, a[:, c] ** 2, minlength=n), 1e-12)
                             for c in range(3)], 1), 0, 1)


def _linear(x: np.ndarray, space: str) -> np.ndarray:
    """Colours in ``space`` as linear light, clipped to [0, 1]."""
    x = np.clip(x, 0, 1)
    return srgb_to_linear(x) if space == "srgb" else x


def _usable(seen: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Sightings (linear light) that carry exposure information: neither dark nor clipped."""
    return (seen > DARK) & (predicted > DARK) & (seen < 0.99)


def predicted_colours(obs: Observations, est: MediumEstimate | None) -> np.ndarray:
    """What the fitted water (None: no water) predicts for each sighting, with each point's colour J solved in
    closed form from its sightings (the fit's variable projection): ``J_p·e^(−β_D r) + B∞(1 − e^(−β_B r))``.
    Sightings of points seen once are NaN (they carry no range information and were not fitted). [M, 3]"""
    counts = np.bincount(obs.point) if obs.point.size else np.zeros(0, np.int64)
    keep = counts[obs.point] >= 2
    out = np.full(obs.colour.shape, np.nan)
    if not keep.any():
        return out
    _, inv = np.unique(obs.point[keep], return_inverse=True)
    a, b = _water(obs.range[keep], est)
    out[keep] = _point_colours(inv, obs.colour[keep], a, b, int(inv.max()) + 1)[inv] * a + b
    return out


def view_prior(view_mean: np.ndarray | None, n_views: int, space: str) -> np.ndarray:
    """Each view's log mean brightness (linear light) relative to the survey's, per channel [V, 3]: the prior mean
    of its log gains (:mod:`pipeline.medium.exposure_gains`); 0 where the views' means were not recorded."""
    if view_mean is None or len(view_mean) != n_views:
        return np.zeros((n_views, 3))
    return mean_neutral(np.log(np.maximum(_linear(np.asarray(view_mean, np.float64), space), 1e-4)))


def view_log_gains(seen: np.ndarray, predicted: np.ndarray, view: np.ndarray, n_views: int, space: str,
                   xy: np.ndarray | None = None, prior: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each view's log gains [V, 3], mean-neutral, from log(seen / predicted) in linear light over its usable
    sightings, beside the in-frame fall-off when the sightings' image positions ``xy`` are known
    (:func:`~pipeline.medium.exposure_gains.gains_beside_field`, ``prior``: [V, 3] the gains' prior means, see
    :func:`view_prior`); their standard errors [V, 3]; the field's coefficients [5]. Views without a usable
    sighting get 0 (and do not enter the mean) and an infinite error."""
    s, p = _linear(seen, space), _linear(np.nan_to_num(predicted, nan=-1.0), space)
    ok = [_usable(s[:, c], p[:, c]) for c in range(3)]
    lg, se, theta = gains_beside_field([np.log(s[o, c] / p[o, c]) for c, o in enumerate(ok)], [view[o] for o in ok],
                                       None if xy is None else [xy[o] for o in ok], n_views, prior)
    has = np.isfinite(se).any(axis=1)
    if has.any():
        lg[has] = mean_neutral(lg[has])
    return lg, se, theta


def exposure_evidence(lg: np.ndarray, se: np.ndarray) -> float:
    """How far the views' gains stand out of their noise: Σ (log g / σ)² over views and channels, per degree of
    freedom (3 x (views − 1)); about 1 when a fixed camera's gains are the fit's noise alone."""
    ok = np.isfinite(se).all(axis=1) & (se > 0).all(axis=1)
    if ok.sum() < 2:
        return 0.0
    return float(((lg[ok] / se[ok]) ** 2).sum() / (3 * (ok.sum() - 1)))


def _gains_under(obs: Observations, est: MediumEstimate | None, lg: np.ndarray, theta: np.ndarray, n_views: int,
                 space: str, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to ``steps`` alternations, the water ``est`` held (None: no water), of the points' colours at neutral
    exposure and the views' gains and the in-frame field (:func:`view_log_gains`) from ``lg`` and ``theta``; (the
    gains, their standard errors, the field)."""
    se = np.full((n_views, 3), np.inf)
    prior = view_prior(obs.view_mean, n_views, space)
    for _ in range(steps):
        pred = predicted_colours(replace(obs, colour=neutral(obs.colour, lg[obs.view] + _field_at(obs, theta), space)),
                                 est)
        # the prediction is at neutral exposure without the field: a view's gains and the field take it to the photo
        new, se, theta_new = view_log_gains(obs.colour, pred, obs.view, n_views, space, obs.xy, prior)
        done = max(float(np.abs(new - lg).max()), float(np.abs(theta_new - theta).max())) < 1e-4
        lg, theta = new, theta_new
        if done:
            break
    return lg, se, theta


def fit_with_exposure(obs: Observations, n_views: int, init_optical_depth: Sequence[float] = (0.8, 0.3, 0.25),
                      space: str = "srgb") -> tuple[MediumEstimate | None, np.ndarray]:
    """The water (:func:`fit_medium`) and each view's exposure log gains [V, 3] (linear light, mean-neutral),
    fitted together (module docstring). The estimate's ``log_gains`` holds them too. None (and zero gains) where
    the sightings cannot say anything about range."""
    if obs.view is None:
        raise ValueError("the sightings must record their views to fit exposure")
    lg = np.zeros((n_views, 3))
    theta = np.zeros(FIELD_TERMS)
    est: MediumEstimate | None = None
    evidence, held = 0.0, False
    judge = 0 if obs.xy is None else 1  # the round whose gains decide whether the frames' exposure changed: with
    #  the field, the second (the first water fit saw the sightings with the fall-off in them); a fixed camera's
    #  gains are then held at 1 and the rounds go on for the water and the field
    for k in range(ROUNDS):
        est = fit_medium(replace(obs, colour=neutral(obs.colour, lg[obs.view] + _field_at(obs, theta), space)),
                         init_optical_depth)
        if est is None:
            return None, np.zeros((n_views, 3))
        lg, se, theta = _gains_under(obs, est, lg, theta, n_views, space, INNER)
        if k == judge:
            evidence = exposure_evidence(lg, se)
            held = evidence < EXPOSURE_EVIDENCE  # a fixed camera: the gains are the fit's noise
            if held and obs.xy is None:
                break
        if held:
            lg = np.zeros((n_views, 3))
    assert est is not None
    field = _field_record(theta, obs)
    span = field["field_span"]
    words = "" if span is None else f"; the frame's fall-off (brightest / darkest) {span:.2f}"
    if held:
        log.info("exposure from the sightings: no change between frames (evidence %.1f < %.0f)%s", evidence,
                 EXPOSURE_EVIDENCE, words)
    else:
        log.info("exposure from the sightings (evidence %.0f): gains %.3f-%.3f (R), %.3f-%.3f (G), %.3f-%.3f (B) "
                 "over %d views%s", evidence, *(float(f(np.exp(lg[:, c]))) for c in range(3) for f in (np.min, np.max)),
                 n_views, words)
    return replace(est, log_gains=lg.tolist(), exposure_evidence=evidence, **field), lg


def _field_at(obs: Observations, theta: np.ndarray) -> np.ndarray | float:
    """The in-frame field's log value at each sighting [M, 1] (0 without the sightings' image positions)."""
    return field_values(obs.xy, theta) if obs.xy is not None else 0.0


def _field_record(theta: np.ndarray, obs: Observations) -> dict:
    """The estimate's ``exposure_field`` and ``field_span`` (None without the sightings' image positions)."""
    if obs.xy is None:
        return {"exposure_field": None, "field_span": None}
    return {"exposure_field": np.round(theta, 5).tolist(), "field_span": round(field_span(theta), 4)}


def fit_exposure_only(obs: Observations, n_views: int, space: str = "srgb") -> tuple[np.ndarray, float]:
    """Each view's exposure log gains [V, 3] (mean-neutral) from the sightings with no water between: a point's
    colour is the same in every view but for the view's gains (the start of plain splatting's learned gains,
    ``3dgs``); and their :func:`exposure_evidence` after the first round. Zero gains below
    :data:`EXPOSURE_EVIDENCE`, as :func:`fit_with_exposure` holds them."""
    if obs.view is None:
        raise ValueError("the sightings must record their views to fit exposure")
    zero = np.zeros((n_views, 3))
    lg, se, theta = _gains_under(obs, None, zero, np.zeros(FIELD_TERMS), n_views, space, INNER)
    evidence = exposure_evidence(lg, se)
    if evidence < EXPOSURE_EVIDENCE:
        return zero, evidence
    return _gains_under(obs, None, lg, theta, n_views, space, (ROUNDS - 1) * INNER)[0], evidence
