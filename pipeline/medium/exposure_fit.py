"""The water fit with every view's exposure and white balance measured beside it.

A sighting of point p in view v is ``encode(g_v · L_p,v)`` where L_p,v is what a fixed camera would record through
the water (:mod:`pipeline.scene.exposure`). Left out, a frame-to-frame exposure change is a colour change the
water must explain, and on real video it did not (the RUIE fit put B∞ on its bound, :func:`~pipeline.medium.estimate
.fit_failure`). The fit alternates: the water from the sightings at neutral exposure (:func:`~pipeline.medium
.estimate.fit_medium`), then each view's gains as the median ratio, in linear light, of its sightings to what the
water and the points' colours predict, shrunk towards 1 for views with few sightings and made mean-neutral.

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
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.exposure import mean_neutral, neutral

log = logging.getLogger(__name__)

ROUNDS = 5  # water fits, each followed by the gains' update: on a generated scene with ±30 % gains β_D (G, B)
#  moved 0.023/0.043 → 0.048/0.074 → 0.060/0.083 → 0.067/0.088 → 0.071/0.091 (without the gains: 0.073/0.102)
EXPOSURE_EVIDENCE = 25.0  # exposure_evidence above this: the frames' exposure changed; below, the gains are noise and
#  held at 1. Measured: generated scenes of a fixed camera 5-6 (gains 1-1.8 % std, the water model's misfit between
#  near and far views), with ±30 % gains 1,750-2,000; real RUIE video 270 (A188) and 450-650 (B571), gains 8-17 % std
INNER = 10  # gain / point-colour alternations per round
SHRINK_SIGHTINGS = 1.0  # a view's gain is shrunk by n / (n + this) towards 1 (n: its usable sightings)
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


def view_log_gains(seen: np.ndarray, predicted: np.ndarray, view: np.ndarray, n_views: int,
                   space: str) -> tuple[np.ndarray, np.ndarray]:
    """Each view's log gains [V, 3], mean-neutral: the median over its sightings of log(seen / predicted) in linear
    light, shrunk towards 0 by n / (n + ``SHRINK_SIGHTINGS``); and their standard errors [V, 3] (the median's:
    1.253 x 1.483 MAD / √n). Views without a usable sighting get 0 (and do not enter the mean) and an infinite
    error."""
    s, p = _linear(seen, space), _linear(np.nan_to_num(predicted, nan=-1.0), space)
    lg = np.zeros((n_views, 3))
    se = np.full((n_views, 3), np.inf)
    has = np.zeros(n_views, bool)
    for c in range(3):
        ok = _usable(s[:, c], p[:, c])
        ratio = np.log(s[ok, c] / p[ok, c])
        v = view[ok]
        order = np.argsort(v, kind="stable")
        v, ratio = v[order], ratio[order]
        bounds = np.searchsorted(v, np.arange(n_views + 1))
        for k in range(n_views):
            part = ratio[bounds[k]:bounds[k + 1]]
            if part.size:
                med = float(np.median(part))
                lg[k, c] = med * part.size / (part.size + SHRINK_SIGHTINGS)
                se[k, c] = 1.2533 * 1.4826 * float(np.median(np.abs(part - med))) / np.sqrt(part.size)
                has[k] = True
    if has.any():
        lg[has] = mean_neutral(lg[has])
    return lg, se


def exposure_evidence(lg: np.ndarray, se: np.ndarray) -> float:
    """How far the views' gains stand out of their noise: Σ (log g / σ)² over views and channels, per degree of
    freedom (3 x (views − 1)); about 1 when a fixed camera's gains are the fit's noise alone."""
    ok = np.isfinite(se).all(axis=1) & (se > 0).all(axis=1)
    if ok.sum() < 2:
        return 0.0
    return float(((lg[ok] / se[ok]) ** 2).sum() / (3 * (ok.sum() - 1)))


def _gains_under(obs: Observations, est: MediumEstimate | None, lg: np.ndarray, n_views: int, space: str,
                 steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``steps`` alternations, the water ``est`` held (None: no water), of the points' colours at neutral
    exposure and the views' gains (:func:`view_log_gains`) from ``lg``; (the gains, their standard errors)."""
    se = np.full((n_views, 3), np.inf)
    for _ in range(steps):
        pred = predicted_colours(replace(obs, colour=neutral(obs.colour, lg[obs.view], space)), est)
        # the prediction is at neutral exposure: a view's gains are what take it to the photo
        new, se = view_log_gains(obs.colour, pred, obs.view, n_views, space)
        done = float(np.abs(new - lg).max()) < 1e-4
        lg = new
        if done:
            break
    return lg, se


def fit_with_exposure(obs: Observations, n_views: int, init_optical_depth: Sequence[float] = (0.8, 0.3, 0.25),
                      space: str = "srgb") -> tuple[MediumEstimate | None, np.ndarray]:
    """The water (:func:`fit_medium`) and each view's exposure log gains [V, 3] (linear light, mean-neutral),
    fitted together (module docstring). The estimate's ``log_gains`` holds them too. None (and zero gains) where
    the sightings cannot say anything about range."""
    if obs.view is None:
        raise ValueError("the sightings must record their views to fit exposure")
    lg = np.zeros((n_views, 3))
    est: MediumEstimate | None = None
    first: MediumEstimate | None = None
    evidence = 0.0
    for k in range(ROUNDS):
        est = fit_medium(replace(obs, colour=neutral(obs.colour, lg[obs.view], space)), init_optical_depth)
        if est is None:
            return None, np.zeros((n_views, 3))
        first = first or est
        lg, se = _gains_under(obs, est, lg, n_views, space, INNER)
        if k == 0:
            evidence = exposure_evidence(lg, se)
            if evidence < EXPOSURE_EVIDENCE:  # a fixed camera: the gains are the fit's noise
                log.info("exposure from the sightings: no change between frames (evidence %.1f < %.0f)", evidence,
                         EXPOSURE_EVIDENCE)
                zero = np.zeros((n_views, 3))
                return replace(first, log_gains=zero.tolist(), exposure_evidence=evidence), zero
    assert est is not None
    log.info("exposure from the sightings (evidence %.0f): gains %.3f-%.3f (R), %.3f-%.3f (G), %.3f-%.3f (B) over "
             "%d views", evidence, *(float(f(np.exp(lg[:, c]))) for c in range(3) for f in (np.min, np.max)), n_views)
    return replace(est, log_gains=lg.tolist(), exposure_evidence=evidence), lg


def fit_exposure_only(obs: Observations, n_views: int, space: str = "srgb") -> tuple[np.ndarray, float]:
    """Each view's exposure log gains [V, 3] (mean-neutral) from the sightings with no water between: a point's
    colour is the same in every view but for the view's gains (the start of plain splatting's learned gains,
    ``3dgs``); and their :func:`exposure_evidence` after the first round. Zero gains below
    :data:`EXPOSURE_EVIDENCE`, as :func:`fit_with_exposure` holds them."""
    if obs.view is None:
        raise ValueError("the sightings must record their views to fit exposure")
    zero = np.zeros((n_views, 3))
    lg, se = _gains_under(obs, None, zero, n_views, space, INNER)
    evidence = exposure_evidence(lg, se)
    if evidence < EXPOSURE_EVIDENCE:
        return zero, evidence
    return _gains_under(obs, None, lg, n_views, space, (ROUNDS - 1) * INNER)[0], evidence
