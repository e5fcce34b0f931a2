"""How much the same seabed point's colour changes with range, from the sparse model's sightings: steps 1-4 of
the truth-free consistency score (:mod:`pipeline.evaluate.consistency`, which scores a restoration against the
photos with them) and, on the photos alone, the water's cue for ``--mode auto`` (:func:`photo_drift`): water is
what makes a surface's colour change with range, and photos without water do not drift.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pipeline.medium.estimate import Observations

MIN_POINT_RANGE_RATIO = 1.1  # a point's farthest / nearest sighting: below this its slope says nothing
MIN_POINTS = 30  # points seen at clearly different ranges needed for a score
TUKEY_C = 4.685  # Tukey's biweight cut-off in robust standard deviations (95 % efficiency at the normal)
MAD_TO_SIGMA = 1.4826


@dataclass
class PointSlopes:
    """Per point seen at clearly different ranges: its mean colour, its colour's slope against range, the
    slope's precision S_p = Σ (r − r̄)², and its sightings' own spread around its mean (std, per channel)."""

    point: np.ndarray  # [P] int
    level: np.ndarray  # [P, 3]
    slope: np.ndarray  # [P, 3] colour per scene unit
    precision: np.ndarray  # [P]
    spread: np.ndarray  # [P, 3]


def point_slopes(obs: Observations, min_ratio: float = MIN_POINT_RANGE_RATIO) -> PointSlopes:
    """Step 1 of the module docstring: each point's least-squares colour slope against range, for the points
    whose sightings span at least ``min_ratio`` in range."""
    if obs.point.size == 0:
        return PointSlopes(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    pid, inv = np.unique(obs.point, return_inverse=True)
    r = np.asarray(obs.range, np.float64)
    c = np.asarray(obs.colour, np.float64).reshape(-1, 3)
    n = np.bincount(inv, minlength=len(pid)).astype(np.float64)
    rmin = np.full(len(pid), np.inf)
    rmax = np.zeros(len(pid))
    np.minimum.at(rmin, inv, r)
    np.maximum.at(rmax, inv, r)
    rbar = np.bincount(inv, r, len(pid)) / n
    cbar = np.stack([np.bincount(inv, c[:, k], len(pid)) for k in range(3)], 1) / n[:, None]
    dr = r - rbar[inv]
    dc = c - cbar[inv]
    srr = np.bincount(inv, dr * dr, len(pid))
    src = np.stack([np.bincount(inv, dr * dc[:, k], len(pid)) for k in range(3)], 1)
    scc = np.stack([np.bincount(inv, dc[:, k] ** 2, len(pid)) for k in range(3)], 1)
    keep = (n >= 2) & (rmax >= min_ratio * np.maximum(rmin, 1e-12)) & (srr > 0)
    slope = src[keep] / srr[keep, None]
    spread = np.sqrt(scc[keep] / (n[keep, None] - 1))
    return PointSlopes(pid[keep], cbar[keep], slope, srr[keep], spread)


def robust_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, iterations: int = 20) -> tuple[float, float]:
    """Step 2: (s_a, s_b) of y ≈ s_a·x + s_b, weighted least squares with precisions ``w`` (y's variance ∝ 1/w),
    iteratively reweighted by Tukey's biweight of the standardised residuals e·√w / σ, σ = 1.4826·MAD of e·√w.
    x, y, w: [P]."""
    X = np.stack([x, np.ones_like(x)], 1)
    u = np.ones_like(x)
    coef = np.zeros(2)
    for _ in range(iterations):
        ww = w * u
        A = X.T @ (ww[:, None] * X)
        if np.linalg.matrix_rank(A) < 2:  # every point at one colour: the offset alone
            coef = np.array([0.0, float(np.sum(ww * y) / max(np.sum(ww), 1e-300))])
        else:
            coef = np.linalg.solve(A, X.T @ (ww * y))
        z = (y - X @ coef) * np.sqrt(w)
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(z - np.median(z))))
        if sigma <= 0:
            break
        t = z / (TUKEY_C * sigma)
        u_new = np.where(np.abs(t) < 1, (1 - t * t) ** 2, 0.0)
        if np.allclose(u_new, u):
            break
        u = u_new
    return float(coef[0]), float(coef[1])


@dataclass
class ChannelDrift:
    """Per channel (R, G, B): the fitted line of slope against colour, the drift over the range spread, the
    points' contrast, the sightings' median spread around their point's mean, and score = drift / contrast."""

    slope_gain: list[float]  # s_a, 1/scene-unit
    slope_offset: list[float]  # s_b, colour per scene unit
    drift: list[float]  # colour units over the range spread
    contrast: list[float]  # colour units
    spread: list[float]  # colour units: median over the points of their sightings' std
    score: list[float | None]  # drift / contrast; None where the contrast is 0

    def to_dict(self) -> dict:
        return asdict(self)


def channel_drift(s: PointSlopes, range_spread: float) -> ChannelDrift:
    """Steps 2-4 of the module docstring for the points ``s``, with Δr = ``range_spread``."""
    out: dict[str, list] = {k: [] for k in ("slope_gain", "slope_offset", "drift", "contrast", "spread",
                                                   "score")}
    for k in range(3):
        a, b = robust_line(s.level[:, k], s.slope[:, k], s.precision)
        g = a * s.level[:, k] + b
        drift = float(np.sqrt(np.mean(g * g))) * range_spread
        lv = s.level[:, k]
        contrast = MAD_TO_SIGMA * float(np.median(np.abs(lv - np.median(lv))))
        out["slope_gain"].append(a)
        out["slope_offset"].append(b)
        out["drift"].append(drift)
        out["contrast"].append(contrast)
        out["spread"].append(float(np.median(s.spread[:, k])))
        out["score"].append(drift / contrast if contrast > 0 else None)  # type: ignore[arg-type]
    return ChannelDrift(**out)


def range_span(obs: Observations, points: np.ndarray) -> tuple[float, float]:
    """(90th / 10th percentile ratio, 90th − 10th difference) of the ranges of ``obs``'s sightings of ``points``
    (the points seen at clearly different ranges): how far the survey's scored sightings reach, Δr of step 3."""
    q10, q90 = np.percentile(obs.range[np.isin(obs.point, points)], [10, 90])
    return float(q90 / max(q10, 1e-12)), float(q90 - q10)


def photo_drift(obs: Observations, min_points: int = MIN_POINTS, min_range_ratio: float = 1.2) -> dict:
    """The photos' own drift with range (``obs``: sightings with the photos' sRGB colours at neutral exposure):
    ``score`` = the largest over the channels of drift / contrast (steps 1-4), ``scores`` per channel,
    ``n_points``, ``range_ratio`` (90th / 10th percentile of the scored sightings' ranges); ``defined`` False with
    the ``reason`` when too few points were seen at clearly different ranges or the survey's ranges span less
    than ``min_range_ratio`` (a constant-altitude line: its colours cannot drift much, water or none).

    Water is what makes a surface's colour change with range: without water the same point keeps its colour
    from near and far. Measured (largest channel; 24-view generated scenes and the real sets at the fast preset's
    training size): without water 0.003-0.007, 0.019-0.12 with a lens's blur growing with range; with water
    1.2-1.5 (generated clear, medium, turbid), RUIE 0.31 / 0.70 and their first 12 frames 0.29 / 0.81, AIMS
    0.65 / 1.10 (docs/DECISIONS.md, "Automatic mode")."""
    sp = point_slopes(obs)
    out: dict = {"defined": False, "reason": None, "score": None, "scores": None, "n_points": len(sp.point),
                 "range_ratio": None}
    if len(sp.point) < min_points:
        out["reason"] = (f"only {len(sp.point)} sparse points were seen at clearly different ranges "
                         f"({min_points} needed)")
        return out
    ratio, spread = range_span(obs, sp.point)
    out["range_ratio"] = round(ratio, 3)
    d = channel_drift(sp, spread)
    if any(s is None for s in d.score):
        out["reason"] = "the photos' colours at the sparse points do not differ in some channel (no contrast)"
        return out
    out["scores"] = [round(float(s), 4) for s in d.score]  # type: ignore[arg-type]
    out["score"] = max(out["scores"])
    if out["range_ratio"] < min_range_ratio:
        out["reason"] = (f"the sightings' ranges span only {out['range_ratio']:.2f}x (< {min_range_ratio:g}x): too "
                         "little for the colours to drift, water or none")
        return out
    out["defined"] = True
    return out
