"""The medium of a view as per-pixel effective coefficients (:class:`~pipeline.restore.records.MediumMaps`).

A network medium renders A and B maps that depend on the pixel's range; to re-evaluate them at the photo's
full-resolution range we turn them into coefficients k_A = −ln A / r and k_B = −ln(1 − B/B∞) / r, which are
smooth where A and B jump with depth. Pixels where r ≈ 0, where alpha < 0.5 or where the inversion saturates
(A ≤ e⁻⁸⁰, B ≥ B∞) get the push-pull fill of their valid neighbours, or the homogeneous fallback when given.
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.restore.guided import fill_invalid
from pipeline.restore.records import MediumMaps

logger = logging.getLogger(__name__)

MIN_RANGE = 1e-3  # scene units; below it a coefficient is not identifiable from A, B
MAX_EXPONENT = 80.0  # as pipeline.medium.formation


def coefficients_from_maps(A: np.ndarray, B: np.ndarray, r: np.ndarray, B_inf: np.ndarray,
                           alpha: np.ndarray | None = None) -> MediumMaps:
    """Effective coefficients from a rendered medium at low resolution.

    Args:
        A, B: [h, w, 3] the rendered direct transmission (0, 1] and backscatter [0, B∞).
        r: [h, w] the range those were evaluated at (distance along the ray, scene units).
        B_inf: [3] veiling light.
        alpha: [h, w] coverage; pixels with alpha < 0.5 are filled from their neighbours.
    Returns MediumMaps with k_A, k_B float32 [h, w, 3], finite and ≥ 0 everywhere (all zeros when no pixel
    is valid)."""
    A, B = np.asarray(A, np.float64), np.asarray(B, np.float64)
    r = np.asarray(r, np.float64)
    binf = np.asarray(B_inf, np.float64).reshape(3)
    ok = np.isfinite(r) & (r > MIN_RANGE)
    if alpha is not None:
        ok &= np.asarray(alpha) >= 0.5
    rr = np.where(ok, r, 1.0)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        kA = -np.log(np.clip(A, np.exp(-MAX_EXPONENT), 1.0)) / rr
        frac = np.clip(B / np.where(binf > 0, binf, 1.0), 0.0, 1.0)
        kB = -np.log1p(-np.minimum(frac, 1.0 - np.exp(-MAX_EXPONENT))) / rr
    sat = (A <= np.exp(-MAX_EXPONENT)).any(-1) | (frac >= 1.0 - 1e-6).any(-1)
    valid = ok & ~sat & np.isfinite(kA).all(-1) & np.isfinite(kB).all(-1)
    if not valid.all():
        logger.debug("medium coefficients: %d of %d pixels filled from neighbours", (~valid).sum(), valid.size)
    k = fill_invalid(np.concatenate([kA, kB], -1), valid)
    k = np.clip(np.nan_to_num(k, nan=0.0, posinf=0.0), 0.0, None).astype(np.float32)
    return MediumMaps(k[..., :3].copy(), k[..., 3:].copy(), binf.copy())


def water_sigma(train_result: dict | None) -> np.ndarray | None:
    """The water's uncertainty [3, 3] (rows σ of log k_A, log k_B, logit B∞; columns channels) from a job's
    train.json: the posterior σ of the sparse points' fit (``pipeline.medium.estimate``; a coefficient the fit
    could not determine is NaN, i.e. the water type's prior width downstream). None when nothing measured the
    water: :data:`pipeline.restore.dewater.UNMEASURED_SIGMA` then."""
    est = ((train_result or {}).get("medium") or {}).get("estimate") or {}
    unc = est.get("uncertainty") or {}
    try:
        rows = [[np.nan if x is None else float(x) for x in unc[k]["sigma"]] for k in ("beta_D", "beta_B", "B_inf")]
        return np.asarray(rows, np.float64).reshape(3, 3)
    except (KeyError, TypeError, ValueError):
        return None
