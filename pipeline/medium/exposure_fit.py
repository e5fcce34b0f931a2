"""The water fit with every view's exposure and white balance measured beside it.

A sighting of point p in view v is ``encode(g_v · L_p,v)`` where L_p,v is what a fixed camera would record through
the water (:mod:`pipeline.scene.exposure`). Left out, a frame-to-frame exposure change is a colour change the
water must explain, and on real video it did not (the RUIE fit put B∞ on its bound, :func:`~pipeline.medium.estimate
.fit_failure`). First the water from the sightings at neutral exposure (:func:`~pipeline.medium.estimate
.fit_medium`) and each view's gains as the median ratio, in linear light, of its sightings to what the water and
the points' colours predict: that first round says whether the exposure changed at all
(:func:`exposure_evidence`). Where it did, the water and the gains are then fitted jointly, one least-squares
problem per channel (:func:`_fit_jointly`), and the water fitted once more at the joint gains for its report.

What separates a gain from the water is range within a view: a gain multiplies every sighting of the view alike,
the water changes them with range. Only a joint fit lets that within-view variation decide; alternating the two
fits let a view's gain absorb the attenuation over its mean range, and on a generated scene with ±30 % gains and
SfM poses it put β_D (G, B) 14 % and 23 % above a fixed camera's (the joint fit: 10 % and 9 %, within what freeing
the gains costs a fixed camera's own fit, 4-6 %). Training refines both (:mod:`pipeline.train.exposure`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch

from pipeline.medium.estimate import MediumEstimate, Observations, Prior, fit_medium, water_type_prior
from pipeline.scene.colour import linear_to_srgb, srgb_to_linear
from pipeline.scene.exposure import mean_neutral, neutral

log = logging.getLogger(__name__)

ROUNDS = 5  # fit_exposure_only: rounds of INNER gain / point-colour alternations
EXPOSURE_EVIDENCE = 25.0  # exposure_evidence above this: the frames' exposure changed; below, the gains are noise and
#  held at 1. Measured: generated scenes of a fixed camera 5-6 (gains 1-1.8 % std, the water model's misfit between
#  near and far views), with ±30 % gains 1,750-2,000; real RUIE video 270 (A188) and 450-650 (B571), gains 8-17 % std
INNER = 10  # gain / point-colour alternations per round
SHRINK_SIGHTINGS = 1.0  # a view's gain is shrunk by n / (n + this) towards 1 (n: its usable sightings)
DARK = 0.01  # linear light: sightings darker than this (predicted or seen) carry no exposure information
CLIPPED = 0.99  # sightings this bright (as recorded) are left out of the joint fit: a clipped value is no gain's
GAIN_PRIOR_SIGMA = 0.5  # the joint fit holds each log gain near 0 with this σ, worth one sighting's misfit: a view
#  seen by a handful of points keeps a gain near 1 instead of one that fits its noise
SRGB_GAIN_POWER = 1 / 2.4  # on sRGB values a gain g scales an encoded value by about g^(1/2.4) (the curve's power)


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


def joint_loss(x: torch.Tensor, inv: torch.Tensor, n_points: int, r: torch.Tensor, seen: torch.Tensor,
               view: torch.Tensor, space: str) -> torch.Tensor:
    """One channel's misfit for x = (log β_D, log β_B, logit B∞, the views' log gains [V]) with every point's J
    eliminated in closed form: the mean over sightings of (w·(J·a + b − n))², where n is the sighting at neutral
    exposure (:func:`~pipeline.scene.exposure.neutral` of ``seen``) and w = g^k the gain's scale on the recorded
    value (k 1 on linear light, :data:`SRGB_GAIN_POWER` on sRGB values), so the misfit is the recorded values'
    and a darkened view does not fit better than a brightened one. J_p = Σ w²a(n − b) / Σ w²a², clamped to
    [0, 1]. Differentiable in x (the fit's autograd objective)."""
    a = torch.exp(-torch.exp(x[0]) * r)
    b = torch.sigmoid(x[2]) * (1 - torch.exp(-torch.exp(x[1]) * r))
    lg = x[3:][view]
    if space == "linear":
        n, w = seen * torch.exp(-lg), torch.exp(lg)
    else:
        n, w = linear_to_srgb(srgb_to_linear(seen) * torch.exp(-lg)), torch.exp(SRGB_GAIN_POWER * lg)
    w2 = w * w
    num = torch.zeros(n_points, dtype=r.dtype).index_add(0, inv, w2 * a * (n - b))
    den = torch.zeros(n_points, dtype=r.dtype).index_add(0, inv, w2 * a * a)
    J = (num / den.clamp(min=1e-12)).clamp(0, 1)
    return ((w * (J[inv] * a + b - n)) ** 2).mean()


def _solve_channel(x0: list[float], pr: Prior, inv: torch.Tensor, n_points: int, r: torch.Tensor,
                   seen: torch.Tensor, view: torch.Tensor, space: str) -> np.ndarray:
    """One channel's joint fit by L-BFGS from x0 = (θ, log gains): the misfit (:func:`joint_loss`) in units of
    its start (at its natural size, ~1e-5, L-BFGS stopped early in the veil's β_B·B∞ valley), the water type's
    prior ``pr`` and the gains' prior in the units fit_medium puts priors in. Returns x [3 + V]."""
    x = torch.tensor(x0, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        s0 = max(float(joint_loss(x, inv, n_points, r, seen, view, space)), 1e-12)
    opt = torch.optim.LBFGS([x], lr=1, max_iter=500, tolerance_grad=1e-12, tolerance_change=1e-15,
                            line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        z = torch.cat([x[:3], x[3:] - x[3:].mean()])  # the gains stay mean-neutral
        loss = (joint_loss(z, inv, n_points, r, seen, view, space) / s0
                + (pr.penalty(z[:3]) + ((z[3:] / GAIN_PRIOR_SIGMA) ** 2).sum()) / len(r))
        loss.backward()
        return loss

    opt.step(closure)  # type: ignore[arg-type]
    return x.detach().numpy()


def _fit_jointly(obs: Observations, est: MediumEstimate, lg: np.ndarray, space: str,
                 init_optical_depth: Sequence[float]) -> np.ndarray:
    """The views' log gains [V, 3] (mean-neutral) from the joint least-squares fit of the water and the gains,
    one channel at a time (:func:`_solve_channel`) from ``est`` and ``lg``, the water under the water type's prior
    as :func:`~pipeline.medium.estimate.fit_medium` puts it and each log gain under :data:`GAIN_PRIOR_SIGMA`.
    Clipped sightings are left out; points need two sightings."""
    out = lg.copy()
    for c in range(3):
        ok = obs.colour[:, c] < CLIPPED
        ok &= np.bincount(obs.point[ok], minlength=int(obs.point.max()) + 1)[obs.point] >= 2
        if not ok.any():
            continue
        _, inv = np.unique(obs.point[ok], return_inverse=True)
        r = torch.as_tensor(obs.range[ok], dtype=torch.float64)
        pr = water_type_prior(max(float(init_optical_depth[c]), 1e-3), float(r.median()))
        theta = [np.log(est.beta_D[c]), np.log(est.beta_B[c]), np.log(est.B_inf[c] / (1 - est.B_inf[c]))]
        x = _solve_channel(theta + list(lg[:, c]), pr, torch.as_tensor(inv), int(inv.max()) + 1, r,
                           torch.as_tensor(obs.colour[ok, c], dtype=torch.float64), torch.as_tensor(obs.view[ok]),
                           space)
        out[:, c] = x[3:]
    return mean_neutral(out)


def fit_with_exposure(obs: Observations, n_views: int, init_optical_depth: Sequence[float] = (0.8, 0.3, 0.25),
                      space: str = "srgb") -> tuple[MediumEstimate | None, np.ndarray]:
    """The water (:func:`fit_medium`) and each view's exposure log gains [V, 3] (linear light, mean-neutral),
    fitted together (module docstring). The estimate's ``log_gains`` holds them too. None (and zero gains) where
    the sightings cannot say anything about range."""
    if obs.view is None:
        raise ValueError("the sightings must record their views to fit exposure")
    zero = np.zeros((n_views, 3))
    first = fit_medium(obs, init_optical_depth)
    if first is None:
        return None, zero
    lg, se = _gains_under(obs, first, zero, n_views, space, INNER)
    evidence = exposure_evidence(lg, se)
    if evidence < EXPOSURE_EVIDENCE:  # a fixed camera: the gains are the fit's noise
        log.info("exposure from the sightings: no change between frames (evidence %.1f < %.0f)", evidence,
                 EXPOSURE_EVIDENCE)
        return replace(first, log_gains=zero.tolist(), exposure_evidence=evidence), zero
    lg = _fit_jointly(obs, first, lg, space, init_optical_depth)
    est = fit_medium(replace(obs, colour=neutral(obs.colour, lg[obs.view], space)), init_optical_depth)
    assert est is not None  # the same points as the first fit's
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
