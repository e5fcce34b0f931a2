"""Bilinear sampling of render-camera maps (depth, alpha, medium coefficients) at the photo pixels' positions."""

from __future__ import annotations

import numpy as np

from pipeline.restore._kernels import sample_bilinear
from pipeline.scene.records import Camera


def sample_maps(maps: np.ndarray, xn: np.ndarray, yn: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``maps`` [h, w, C] (render ``camera``) at the rays xn, yn [n, W] of photo pixels.

    Bilinear, pixel-centre convention (u = fx·xn + cx; map pixel (i, j) sits at (j + 0.5, i + 0.5)), clamped to
    the edge. Returns (values [n, W, C] float32, inside [n, W] bool: the ray lands inside the render image)."""
    return sample_bilinear(np.ascontiguousarray(maps, dtype=np.float32), np.ascontiguousarray(xn, np.float32),
                           np.ascontiguousarray(yn, np.float32), float(camera.fx), float(camera.fy),
                           float(camera.cx), float(camera.cy))


def sample_maps_reference(maps: np.ndarray, xn: np.ndarray, yn: np.ndarray,
                          camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Slow twin of :func:`sample_maps` (plain numpy, float64). Same shapes."""
    h, w, _ = maps.shape
    u = camera.fx * np.asarray(xn, np.float64) + camera.cx
    v = camera.fy * np.asarray(yn, np.float64) + camera.cy
    inside = (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
    x, y = np.clip(u - 0.5, 0, w - 1), np.clip(v - 0.5, 0, h - 1)
    x0, y0 = np.minimum(x.astype(int), max(w - 2, 0)), np.minimum(y.astype(int), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    s, t = (x - x0)[..., None], (y - y0)[..., None]
    m = np.asarray(maps, np.float64)
    out = (m[y0, x0] * (1 - s) + m[y0, x1] * s) * (1 - t) + (m[y1, x0] * (1 - s) + m[y1, x1] * s) * t
    return out, inside
