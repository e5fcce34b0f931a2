"""Depth from the low-resolution render to the photo's resolution, with edges that follow the photo.

Steps: fill the render's no-surface pixels with nearby surface depth (push-pull, :func:`fill_invalid`) so no
zero depth bleeds into the surface; sample the filled depth and alpha bilinearly through the lens map; filter
the depth with He's guided filter (He, Sun & Tang 2013) guided by the photo's luminance, radius ≈ the upsampling
factor, in its fast form (He & Sun 2015: the linear coefficients a, b computed on s×s block means, then
interpolated; q = a·I + b at full resolution, so edges come from the full-resolution photo); the caller
re-masks with the sampled alpha ≥ 0.5. Row bands starting at multiples of s with :func:`halo_rows` of halo give
exactly the whole-frame result. Choice of radius and eps: docs/DECISIONS.md, "Restoring
the originals".
"""

from __future__ import annotations

import numpy as np

from pipeline.scene.records import Camera, LensCamera

DEFAULT_EPS = 1e-4  # guide luminance variance units (luminance in [0, 1]); measured: bench/restore.py --filter


def upsampling_factor(lens: LensCamera, camera: Camera, pad: int = 0) -> float:
    """Photo pixels per render pixel: photo width / render width, the render's width without the ``pad`` pixels
    :func:`pipeline.restore.views.photo_view` added on each side."""
    return lens.width / (camera.width - 2 * pad)


def default_radius(lens: LensCamera, camera: Camera, pad: int = 0) -> int:
    """The filter radius in photo pixels: half the :func:`upsampling_factor`, at least 1 (a radius of the whole
    factor blurs a depth step more than bilinear does: bench/restore.py --filter)."""
    return max(1, round(upsampling_factor(lens, camera, pad) / 2))


def default_subsample(radius: int) -> int:
    """The fast guided filter's block size for ``radius``: radius // 2, at least 1 (two low-res pixels of
    radius)."""
    return max(1, radius // 2)


def fill_invalid(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """x [h, w, C] with the pixels where ``valid`` [h, w] is False replaced by a push-pull average of the valid
    ones nearby (2×2 pyramid, valid-weighted); all zeros when nothing is valid. float64 [h, w, C]."""
    x = np.asarray(x, np.float64)
    valid = np.asarray(valid, bool)
    if valid.all():
        return x.copy()
    if not valid.any():
        return np.zeros_like(x)
    h, w, C = x.shape
    H2, W2 = (h + 1) // 2, (w + 1) // 2
    wsum = np.zeros((H2 * 2, W2 * 2))
    vsum = np.zeros((H2 * 2, W2 * 2, C))
    wsum[:h, :w] = valid
    vsum[:h, :w] = np.where(valid[..., None], x, 0.0)
    ws = wsum.reshape(H2, 2, W2, 2).sum((1, 3))
    vs = vsum.reshape(H2, 2, W2, 2, C).sum((1, 3))
    coarse = fill_invalid(vs / np.maximum(ws, 1)[..., None], ws > 0)
    up = np.repeat(np.repeat(coarse, 2, 0), 2, 1)[:h, :w]
    return np.where(valid[..., None], x, up)


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """He's guided filter with a grey guide: guide, src [H, W] → [H, W] float32. Windows are (2r+1)² clipped to
    the image (means over the pixels inside). O(1) per pixel (numba running sums)."""
    # lazy: numba (and torch) load at the first kernel call; the numpy twins and constants here need neither
    from pipeline.restore._kernels import box_mean, guided_apply, guided_coeffs, guided_stats

    g = np.ascontiguousarray(guide, np.float32)
    p = np.asarray(src, np.float32)
    off = np.float32(p.mean()) if p.size else np.float32(0)  # centred source: no float32 cancellation in cov
    m = box_mean(guided_stats(g, np.ascontiguousarray(p - off)), int(radius))
    mab = box_mean(guided_coeffs(m, float(eps)), int(radius))
    return guided_apply(mab, g) + off


def fast_guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float, s: int) -> np.ndarray:
    """The fast guided filter: :func:`guided_filter` on s×s block means with radius max(1, round(radius / s)),
    the coefficients interpolated back to full resolution. guide, src [H, W] → [H, W] float32.
    s = 1 equals :func:`guided_filter` (up to float rounding)."""
    # lazy: numba (and torch) load at the first kernel call; the numpy twins and constants here need neither
    from pipeline.restore._kernels import block_mean, box_mean, guided_coeffs, guided_stats, upsample_apply

    g = np.ascontiguousarray(guide, np.float32)
    p = np.asarray(src, np.float32)
    off = np.float32(p.mean()) if p.size else np.float32(0)
    g_lo, p_lo = block_mean(g, int(s)), block_mean(np.ascontiguousarray(p - off), int(s))
    r = max(1, round(radius / s))
    m = box_mean(guided_stats(g_lo, p_lo), r)
    mab = box_mean(guided_coeffs(m, float(eps)), r)
    return upsample_apply(mab, g, int(s), float(off))


def halo_rows(radius: int, s: int) -> int:
    """Rows of halo a band needs for :func:`fast_guided_filter` to match the whole frame: two box filters of
    the low-resolution radius plus one block for the interpolation, in photo rows (a multiple of s)."""
    return s * (2 * max(1, round(radius / s)) + 2)


def _box_mean_reference(x: np.ndarray, r: int) -> np.ndarray:
    """Slow twin of the box mean: per pixel, the mean of the clipped window. [H, W] float64."""
    H, W = x.shape
    out = np.empty((H, W))
    for i in range(H):
        for j in range(W):
            out[i, j] = x[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].mean()
    return out


def guided_filter_reference(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Slow twin of :func:`guided_filter` (He et al. 2013, Algorithm 1, float64, explicit windows). [H, W]."""
    I, p = np.asarray(guide, np.float64), np.asarray(src, np.float64)
    mI, mp = _box_mean_reference(I, radius), _box_mean_reference(p, radius)
    cov = _box_mean_reference(I * p, radius) - mI * mp
    var = _box_mean_reference(I * I, radius) - mI * mI
    a = cov / (var + eps)
    b = mp - a * mI
    return _box_mean_reference(a, radius) * I + _box_mean_reference(b, radius)
