"""Evaluation metrics as pure functions (numpy in, floats out).

- PSNR over a set of views is computed from the *pooled* MSE (all pixels of all views), not averaged per view.
- SSIM uses an 11×11 Gaussian window with σ = 1.5 (Wang et al. 2004, the 3DGS convention).
- Depth error is measured after a least-squares scale alignment (SfM depth has no metric scale).
- Water coefficients are compared per channel, absolute and relative.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from pipeline.ops.image_losses import ssim as _ssim

ImagePair = tuple[np.ndarray, np.ndarray] | tuple[torch.Tensor, torch.Tensor]


def _float64(pred: np.ndarray | torch.Tensor, gt: np.ndarray | torch.Tensor) -> tuple[Any, Any]:
    """The pair in float64, as tensors when either is one (summed by torch, as training's held-out curve always
    was) and as arrays otherwise (summed by numpy)."""
    if isinstance(pred, torch.Tensor) or isinstance(gt, torch.Tensor):
        return torch.as_tensor(pred).detach().double(), torch.as_tensor(gt).detach().double()
    return np.asarray(pred, np.float64), np.asarray(gt, np.float64)


def pooled_mse(pairs: Sequence[ImagePair], masks: Sequence[np.ndarray] | None = None) -> float:
    """Mean squared error over every pixel of every (prediction, target) pair, each [H, W, 3] in [0, 1] (numpy
    arrays or torch tensors); with ``masks`` ([H, W] bool per pair) only over the pixels they keep (NaN when
    they keep none)."""
    if not pairs:
        raise ValueError("no image pairs to score")
    if masks is not None and len(masks) != len(pairs):
        raise ValueError(f"{len(masks)} masks for {len(pairs)} image pairs")
    se, n = 0.0, 0
    for k, (pred, gt) in enumerate(pairs):
        if pred.shape != gt.shape:
            raise ValueError(f"prediction {tuple(pred.shape)} and target {tuple(gt.shape)} differ")
        a, b = _float64(pred, gt)
        d = a - b
        if masks is not None:
            if masks[k].shape != d.shape[:2]:
                raise ValueError(f"mask {masks[k].shape} does not fit image {tuple(d.shape)}")
            d = d[torch.as_tensor(masks[k]) if isinstance(d, torch.Tensor) else masks[k]]
        se += float((d * d).sum())
        n += math.prod(d.shape)
    return se / n if n else math.nan


def psnr(mse: float) -> float:
    """PSNR in dB for images in [0, 1]; +inf for a perfect match."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def pooled_psnr(pairs: Sequence[ImagePair], masks: Sequence[np.ndarray] | None = None) -> float:
    """PSNR of the pooled MSE (over the masked pixels when ``masks`` are given; NaN when none are kept): not a
    mean of per-view PSNRs. Inputs are clamped by the caller if needed."""
    mse = pooled_mse(pairs, masks)
    return math.nan if math.isnan(mse) else psnr(mse)


def mean_ssim(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """SSIM (11×11 Gaussian window, σ 1.5) averaged over views."""
    vals = [float(_ssim(torch.as_tensor(p, dtype=torch.float32), torch.as_tensor(g, dtype=torch.float32)))
            for p, g in pairs]
    return float(np.mean(vals))


def scale_aligned_depth_error(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray],
                              masks: Sequence[np.ndarray] | None = None) -> dict[str, float]:
    """Depth error after one least-squares scale s minimising Σ(s·pred − gt)² over all valid pixels.

    Returns the scale, mean absolute error (gt units) and mean relative error |s·pred − gt| / gt.
    """
    p = np.concatenate([np.asarray(x, np.float64).ravel() for x in pred])
    g = np.concatenate([np.asarray(x, np.float64).ravel() for x in gt])
    valid = np.isfinite(p) & np.isfinite(g) & (g > 0) & (p > 0)
    if masks is not None:
        valid &= np.concatenate([np.asarray(m, bool).ravel() for m in masks])
    if not valid.any():
        raise ValueError("no valid depth pixels to compare")
    p, g = p[valid], g[valid]
    s = float((p * g).sum() / (p * p).sum())
    err = np.abs(s * p - g)
    return {"scale": s, "abs_error": float(err.mean()), "rel_error": float((err / g).mean()),
            "n_pixels": int(valid.sum())}


def per_metre(coefficients: Sequence[float], metres_per_unit: float) -> list[float]:
    """Attenuation or backscatter coefficients from 1/scene-unit to 1/m, given how many metres one scene unit is
    (the alignment to the truth, or the user's metric scale)."""
    per_m = 1.0 / metres_per_unit
    return [b * per_m for b in coefficients]


def coefficient_error(estimated: Sequence[float], true: Sequence[float]) -> dict[str, list[float]]:
    """Per-channel absolute and relative error of a water coefficient (β_D, β_B or B∞)."""
    e, t = np.asarray(estimated, np.float64), np.asarray(true, np.float64)
    return {"estimated": e.tolist(), "true": t.tolist(), "abs_error": np.abs(e - t).tolist(),
            "rel_error": (np.abs(e - t) / np.maximum(np.abs(t), 1e-9)).tolist()}
