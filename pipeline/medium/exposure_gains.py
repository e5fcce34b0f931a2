"""Each view's exposure gains measured beside the survey's in-frame fall-off.

A photo is darker at some places of the frame than at others whatever it shows: the lens's vignetting, a lamp's
cone, the sun's fall-off over a wide frame. The field is the same in every view, a multiplicative ``V(x, y)`` over
image coordinates. Left out of the gains' fit, it is read as exposure wherever the points cross the frame the same
way from one view to the next, as they do on a towed camera's line: on the AIMS Erub line a point is ~20 % darker
at the frame's top than at its bottom and moves 17 % of the frame's height a frame, so it brightens by ~8 % from
one frame to the next, and the per-view medians chained that into gains of 0.69 → 1.35 along a line whose photos'
mean brightness is constant within 5 % (the restored photos darkened 2.5x along it).

So a sighting's log ratio to what the water predicts is ``x_v,c + θ·f(x, y) + noise``: the view's log gain per
channel plus a log-quadratic field ``f = (x, y, x², y², xy)`` (coordinates in half-widths and half-heights from
the centre), one robust least-squares problem (Huber weights, iterated). The field is the same in every channel:
vignetting and a light's cone are grey, while the water's own change over a frame (farther at its edges, or at its
top for an oblique camera) is coloured and stays the water's; a field per channel took 14x over the frame in
RUIE B571's red. On a line at constant speed a gain ramp and a field tilted along the motion explain the
sightings alike; the photos' own mean brightness decides between them: each view's log gain has a prior at the
log of its photo's mean over the survey's (what an exposure change does to a photo of a survey whose content does
not drift), loose enough (:data:`PRIOR_SIGMA`) that the sightings decide wherever they can.
"""

from __future__ import annotations

import numpy as np

FIELD_TERMS = 5  # x, y, x², y², xy
PRIOR_SIGMA = 0.2  # log units: a view's gain about its photo's relative mean brightness (the content's variation
#  from frame to frame: Erub's photo means 5 %, a generated survey's views at different ranges ~15 %)
FIELD_SIGMA = 0.3  # log units: the prior on each field coefficient (AIMS Erub's fall-off: 0.2-0.3 per term)
HUBER = 1.345  # Huber's threshold in robust standard deviations (95 % efficiency on Gaussian noise)
IRLS_STEPS = 6
START_SIGMA = 0.05  # log units: the sightings' noise assumed for the first step (then measured: 1.48 MAD)


def field_basis(xy: np.ndarray) -> np.ndarray:
    """The field's terms at image positions ``xy`` [M, 2] (half-widths / half-heights from the centre). [M, 5]"""
    x, y = xy[:, 0], xy[:, 1]
    return np.stack([x, y, x * x, y * y, x * y], 1)


def field_values(xy: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The log field [M, 1] at ``xy`` for coefficients ``theta`` [5] (the same in every channel)."""
    return (field_basis(xy) @ np.asarray(theta, np.float64))[:, None]


def field_map(width: int, height: int, theta: np.ndarray) -> np.ndarray:
    """The log field [height, width] of coefficients ``theta`` [5] over an image of that size (the training
    camera's, undistorted), at its pixel centres: column j sits at x = 2(j + ½)/width − 1, as a sighting at COLMAP's
    pixel coordinate u sits at 2u/width − 1."""
    x = 2 * (np.arange(width) + 0.5) / width - 1
    y = 2 * (np.arange(height) + 0.5) / height - 1
    xy = np.stack(np.meshgrid(x, y), -1).reshape(-1, 2)
    return field_values(xy, theta).reshape(height, width)


def field_span(theta: np.ndarray, grid: int = 21) -> float:
    """How much the field changes over the frame: its brightest over its darkest value."""
    t = np.linspace(-1, 1, grid)
    f = field_values(np.stack(np.meshgrid(t, t), -1).reshape(-1, 2), theta)
    return float(np.exp(f.max() - f.min()))


def _solve(ratio: np.ndarray, index: np.ndarray, basis: np.ndarray, w: np.ndarray, n: int, prior_mean: np.ndarray,
           sigma2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted least squares with both priors: ``n`` gains (one per view and channel, ``index`` into them)
    and the field's coefficients shared by the channels; each row's noise variance ``sigma2`` (its channel's).
    (the unknowns [n + F], the inverse of the normal matrix)."""
    F = basis.shape[1]
    wn = w / sigma2
    H = np.zeros((n + F, n + F))
    b = np.zeros(n + F)
    H[np.arange(n), np.arange(n)] = np.bincount(index, wn, minlength=n) + PRIOR_SIGMA ** -2
    b[:n] = np.bincount(index, wn * ratio, minlength=n) + prior_mean * PRIOR_SIGMA ** -2
    if F:
        cross = np.stack([np.bincount(index, wn * basis[:, j], minlength=n) for j in range(F)], 1)
        H[:n, n:], H[n:, :n] = cross, cross.T
        H[n:, n:] = (basis * wn[:, None]).T @ basis + np.eye(F) * FIELD_SIGMA ** -2
        b[n:] = basis.T @ (wn * ratio)
    cov = np.linalg.inv(H)
    return cov @ b, cov


def gains_beside_field(ratios: list[np.ndarray], views: list[np.ndarray], xys: list[np.ndarray] | None, n_views: int,
                       prior_mean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel c: log(seen / predicted) of its usable sightings ``ratios[c]`` [M_c] in views ``views[c]`` at
    image positions ``xys[c]`` [M_c, 2] (None: no field) as each view's log gain plus the field shared by the
    channels (module docstring). ``prior_mean`` [V, 3]: each view's log mean brightness relative to the survey's
    (None: 0). Returns the log gains [V, 3] (views without a sighting at 0), their standard errors [V, 3] (inf
    where unseen) and the field's coefficients [5] (zero without positions)."""
    C = len(ratios)
    n = n_views * C
    prior = np.zeros(n) if prior_mean is None else np.asarray(prior_mean, np.float64).T.reshape(-1)
    ratio = np.concatenate(ratios)
    channel = np.concatenate([np.full(len(r), c) for c, r in enumerate(ratios)])
    index = np.concatenate([c * n_views + np.asarray(v) for c, v in enumerate(views)]).astype(np.int64)
    basis = (field_basis(np.concatenate(xys)) if xys is not None and len(ratio)
             else np.zeros((len(ratio), FIELD_TERMS if xys is not None else 0)))
    seen = np.bincount(index, minlength=n) > 0
    w = np.ones(len(ratio))
    sigma2 = np.full(C, START_SIGMA ** 2)
    for _ in range(IRLS_STEPS):
        sol, cov = _solve(ratio, index, basis, w, n, prior, sigma2[channel])
        res = ratio - sol[index] - basis @ sol[n:]
        s = np.array([max(1.4826 * float(np.median(np.abs(res[channel == c]))), 1e-4) if (channel == c).any()
                      else START_SIGMA for c in range(C)])
        sigma2 = s * s
        w = np.minimum(1.0, HUBER * s[channel] / np.maximum(np.abs(res), 1e-12))
    sol, cov = _solve(ratio, index, basis, w, n, prior, sigma2[channel])
    lg = np.where(seen, sol[:n], 0.0).reshape(C, n_views).T
    se = np.where(seen, np.sqrt(np.diag(cov)[:n]), np.inf).reshape(C, n_views).T
    theta = sol[n:] if xys is not None else np.zeros(FIELD_TERMS)
    return lg, se, theta


__all__ = ["FIELD_TERMS", "PRIOR_SIGMA", "field_basis", "field_map", "field_span", "field_values", "gains_beside_field"]
