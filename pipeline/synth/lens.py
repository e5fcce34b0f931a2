"""Lens geometry of the generated scenes: COLMAP's ``RADIAL`` model and per-pixel rays through it.

The generator's camera has fx = fy = f (square pixels, principal point at the image centre), so the distorted
camera is COLMAP's ``RADIAL`` model, params ``f, cx, cy, k1, k2`` (COLMAP order): a camera-space point
(X, Y, Z) has normalised coordinates x = X/Z, y = Y/Z, r² = x² + y², and lands at the pixel

    u = f · x · (1 + k1 r² + k2 r⁴) + cx,   v = f · y · (1 + k1 r² + k2 r⁴) + cy

with COLMAP's pixel-centre convention (the top-left pixel's centre is (0.5, 0.5)); this is exactly
``pycolmap.Camera(model="RADIAL", ...).img_from_cam``. Rendering goes the other way: every (sub-)pixel position
of the distorted image is undistorted (Newton on the radius, float64, to < 1e-12) and casts the ray
(x, y, 1). With k1 = k2 = 0 the camera is the plain PINHOLE ``f, f, cx, cy`` and no undistortion runs, so
undistorted scenes are computed exactly as before.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.scene.records import Camera, LensCamera, ray_length_factor

F64 = torch.float64
NEWTON_STEPS = 30


def distortion_pair(value) -> tuple[float, float]:
    """A config's ``distortion`` (any pair-like, e.g. a JSON list) as the (k1, k2) floats of COLMAP's RADIAL."""
    k = tuple(float(x) for x in value)
    if len(k) != 2:
        raise ValueError(f"distortion is (k1, k2), got {value!r}")
    return k  # type: ignore[return-value]


def is_distorted(distortion: tuple[float, float]) -> bool:
    return any(float(k) != 0.0 for k in distortion)


def original_camera(cam: Camera, distortion: tuple[float, float]) -> LensCamera:
    """The true camera of a generated scene: PINHOLE without distortion, else RADIAL (needs fx == fy)."""
    if not is_distorted(distortion):
        return LensCamera("PINHOLE", cam.width, cam.height, (cam.fx, cam.fy, cam.cx, cam.cy))
    if cam.fx != cam.fy:
        raise ValueError(f"RADIAL needs fx == fy, got {cam.fx} and {cam.fy}")
    k1, k2 = (float(k) for k in distortion)
    check_invertible(cam, (k1, k2))
    return LensCamera("RADIAL", cam.width, cam.height, (cam.fx, cam.cx, cam.cy, k1, k2))


def _radial_gain(r2, k1: float, k2: float):
    return 1.0 + k1 * r2 + k2 * r2 * r2


def distort_normalized(x, y, distortion: tuple[float, float]):
    """Undistorted normalised coordinates → distorted normalised ones (numpy or torch, any shape)."""
    k1, k2 = distortion
    g = _radial_gain(x * x + y * y, k1, k2)
    return x * g, y * g


def undistort_normalized(xd: torch.Tensor, yd: torch.Tensor, distortion: tuple[float, float]
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Distorted normalised coordinates → undistorted ones: Newton on r_u·(1 + k1 r_u² + k2 r_u⁴) = r_d."""
    k1, k2 = distortion
    rd = torch.sqrt(xd * xd + yd * yd)
    ru = rd.clone()
    for _ in range(NEWTON_STEPS):
        r2 = ru * ru
        f = ru * _radial_gain(r2, k1, k2) - rd
        df = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
        ru = ru - f / df
    scale = torch.where(rd > 0, ru / rd.clamp(min=1e-300), torch.ones_like(rd))
    return xd * scale, yd * scale


def check_invertible(cam: Camera, distortion: tuple[float, float]) -> None:
    """Raise if the radial map folds over inside the image (its derivative must stay positive out to the
    undistorted radius of the farthest corner), where no unique ray exists."""
    k1, k2 = distortion
    rd = math.hypot(max(cam.cx, cam.width - cam.cx) / cam.fx, max(cam.cy, cam.height - cam.cy) / cam.fy)
    r = torch.linspace(0.0, 1.0, 2001, dtype=F64) * rd * 3.0
    slope = 1.0 + 3.0 * k1 * r * r + 5.0 * k2 * r**4
    image = r * _radial_gain(r * r, k1, k2)
    reach = (image >= rd) & (slope > 0)
    fold = (slope <= 0).nonzero()
    if not reach.any() or (fold.numel() and fold[0, 0] <= reach.nonzero()[0, 0]):
        raise ValueError(f"distortion {distortion} folds over inside the {cam.width}x{cam.height} image "
                         f"(the radial map is not monotonic out to the corner); use weaker coefficients")


def pixel_directions(cam: Camera, distortion: tuple[float, float], supersample: int, rows: tuple[int, int]
                     ) -> torch.Tensor:
    """Camera-space ray directions (x, y, 1) of the supersamples of pixel rows ``rows`` = [r0, r1):
    sub-pixel positions (i + 0.5)/s in distorted image space, undistorted when ``distortion`` is non-zero.
    # [(r1 − r0)·s, W·s, 3] float64"""
    s = supersample
    u = (torch.arange(cam.width * s, dtype=F64) + 0.5) / s
    v = (torch.arange(rows[0] * s, rows[1] * s, dtype=F64) + 0.5) / s
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    x, y = (uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy
    if is_distorted(distortion):
        x, y = undistort_normalized(x, y, distortion)
    return torch.stack([x, y, torch.ones_like(uu)], -1)


def pixel_ray_factor(cam: Camera, distortion: tuple[float, float]) -> np.ndarray:
    """Distance along each pixel-centre ray per unit camera z, sqrt(1 + x² + y²) of the pixel's undistorted
    normalised coordinates (``ray_length_factor`` itself without distortion).  # [H, W]"""
    if not is_distorted(distortion):
        return ray_length_factor(cam)
    d = pixel_directions(cam, distortion, 1, (0, cam.height))
    return torch.linalg.norm(d, dim=-1).numpy()


def project_pixels(cam: Camera, distortion: tuple[float, float], xc: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space points [N, 3] → pixel (u, v) through the lens (pixel-centre convention; NaN/inf for z = 0)."""
    zc = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = xc[:, 0] / zc, xc[:, 1] / zc
        if not is_distorted(distortion):
            return cam.fx * xc[:, 0] / zc + cam.cx, cam.fy * xc[:, 1] / zc + cam.cy
        xd, yd = distort_normalized(x, y, distortion)
    return cam.fx * xd + cam.cx, cam.fy * yd + cam.cy


def row_bands(height: int, rays_per_row: int, max_rays: int) -> list[tuple[int, int]]:
    """Pixel-row bands [r0, r1) of at most ``max_rays`` rays each (at least one row); one band when it fits."""
    step = max(1, max_rays // max(1, rays_per_row))
    return [(r, min(height, r + step)) for r in range(0, height, step)]


__all__ = ["distort_normalized", "distortion_pair", "is_distorted", "original_camera", "pixel_directions",
           "pixel_ray_factor", "project_pixels", "row_bands", "undistort_normalized"]
