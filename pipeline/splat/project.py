"""EWA projection of 3D Gaussians to the image plane (pure torch, differentiable): the reference.

Conventions (gsplat's "classic" pinhole projection, Zwicker et al. 2002 "EWA splatting"):
- ``viewmats`` are ``cam_from_world`` [C, 4, 4]; the camera looks down +z, x right, y down.
- ``Ks`` are pinhole intrinsics [C, 3, 3]; the centre of the top-left pixel is at (0.5, 0.5), so a pixel (i, j)
  is sampled at (j + 0.5, i + 0.5) and ``means2d`` are in pixels.
- Sigma_3d = R S S^T R^T with R from the normalised quaternion (w, x, y, z), S = diag(scales).
- Sigma_2d = J W Sigma_3d W^T J^T + eps2d * I, with J the Jacobian of the perspective map at the camera-space mean,
  whose x/z and y/z are clamped to 1.3x the field of view (keeps huge off-screen Gaussians finite).
- conic = inverse(Sigma_2d) as (a, b, c) = ([0,0], [0,1], [1,1]).
- radii: the opacity-aware box of Radl et al. 2024 (used by gsplat): half-extent along x is
  ceil(k sqrt(Sigma_2d[0,0])) with k = min(3.33, sqrt(2 ln(255 opacity))), the exact extent of the region where
  alpha >= 1/255. A Gaussian is culled (radii 0) if its depth is outside [near, far], its opacity < 1/255, or its
  box misses the image. Culled entries of means2d, conics and depths are 0 (as gsplat's CUDA kernel leaves them).

The computation runs in float64 and rounds the results to the input dtype. The cpu backend's kernel does the same,
so both backends see bit-identical float32 means2d and conics (up to a ~1e-8 chance per value) and therefore
make identical alpha >= 1/255 decisions (see ``_torch_ref``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.splat._constants import ALPHA_MIN, MAX_EXTENT_SIGMAS


@dataclass
class Projection:
    """Per-camera screen-space Gaussians."""

    means2d: Tensor  # [C, N, 2] pixels
    conics: Tensor  # [C, N, 3] inverse 2D covariance (a, b, c)
    depths: Tensor  # [C, N] camera-space z
    radii: Tensor  # [C, N, 2] int32, 0 = culled
    depth_keys: Tensor  # [C, N] float64 camera-space z, the sort key (no grad)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of (not necessarily normalised) quaternions wxyz: [..., 4] -> [..., 3, 3]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R S S^T R^T: quats [N, 4] wxyz, scales [N, 3] (positive) -> [N, 3, 3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]  # [N, 3, 3] = R S
    return m @ m.transpose(-1, -2)


def opacity_extent(opacities: Tensor) -> Tensor:
    """Box half-extent in standard deviations where alpha >= 1/255: [N] -> [N] (NaN-free, 0 below 1/255)."""
    arg = (opacities / ALPHA_MIN).clamp_min(1.0)
    return torch.sqrt(2.0 * torch.log(arg)).clamp_max(MAX_EXTENT_SIGMAS)


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor | None,  # [N] or None (then the 3.33-sigma box)
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Projection:
    """Project N Gaussians into C pinhole cameras (float64 inside, results in ``means.dtype``)."""
    out_dtype = means.dtype
    f64 = torch.float64
    cov = covariance_3d(quats.to(f64), scales.to(f64))  # [N, 3, 3]
    R = viewmats[:, :3, :3].to(f64)  # [C, 3, 3]
    t = viewmats[:, :3, 3].to(f64)  # [C, 3]
    mean_c = torch.einsum("cij,nj->cni", R, means.to(f64)) + t[:, None, :]  # [C, N, 3]
    cov_c = R[:, None] @ cov[None] @ R[:, None].transpose(-1, -2)  # [C, N, 3, 3]

    z = mean_c[..., 2]  # [C, N]
    in_depth = (z >= near_plane) & (z <= far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # keeps culled entries finite (and their grads 0)
    fx, fy = Ks[:, 0, 0, None].to(f64), Ks[:, 1, 1, None].to(f64)  # [C, 1]
    cx, cy = Ks[:, 0, 2, None].to(f64), Ks[:, 1, 2, None].to(f64)
    # Jacobian at a mean whose x/z, y/z are clamped to 1.3x the field of view (gsplat's persp_proj).
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * width / (2 * fx), cx / fx + 0.3 * width / (2 * fx)
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * height / (2 * fy), cy / fy + 0.3 * height / (2 * fy)
    u = mean_c[..., 0] / z_safe  # [C, N]
    v = mean_c[..., 1] / z_safe
    tx = z_safe * torch.maximum(torch.minimum(u, lim_xp), -lim_xn)
    ty = z_safe * torch.maximum(torch.minimum(v, lim_yp), -lim_yn)
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).reshape(z.shape + (2, 3))  # [C, N, 2, 3]
    cov2d = J @ cov_c @ J.transpose(-1, -2) + eps2d * torch.eye(2, dtype=f64, device=means.device)
    a, b, c = cov2d[..., 0, 0], 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]), cov2d[..., 1, 1]
    det = a * c - b * b  # [C, N]
    ok_det = det > 0
    inv_det = 1.0 / torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c * inv_det, -b * inv_det, a * inv_det], dim=-1)  # [C, N, 3]
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)  # [C, N, 2]

    with torch.no_grad():
        if opacities is None:
            ext = torch.full_like(z, MAX_EXTENT_SIGMAS)
            ok_op = torch.ones_like(in_depth)
        else:
            ext = opacity_extent(opacities.to(f64))[None, :].expand_as(z)
            ok_op = (opacities.to(f64) >= ALPHA_MIN)[None, :].expand_as(z)
        rx = torch.ceil(ext * a.detach().clamp_min(0).sqrt())
        ry = torch.ceil(ext * c.detach().clamp_min(0).sqrt())
        mx, my = means2d[..., 0].detach(), means2d[..., 1].detach()
        inside = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        visible = in_depth & ok_det & ok_op & ((rx > 0) | (ry > 0)) & inside  # [C, N]
        radii = torch.stack([rx, ry], dim=-1) * visible[..., None]
        radii = radii.to(torch.int32)
        depth_keys = torch.where(visible, z.detach(), torch.full_like(z, math.inf))

    vis = visible[..., None]
    return Projection(
        means2d=torch.where(vis, means2d, 0.0).to(out_dtype),
        conics=torch.where(vis, conics, 0.0).to(out_dtype),
        depths=torch.where(visible, z, 0.0).to(out_dtype),
        radii=radii,
        depth_keys=depth_keys,
    )
