"""Real spherical harmonics up to degree 3 for view-dependent colour (pure torch, differentiable): the reference.

The basis and its sign convention are those of 3DGS / gsplat (Sloan 2013, "Efficient Spherical Harmonic
Evaluation", JCGT 2(2)), so PLY files trained elsewhere render identically. A Gaussian's colour seen from a camera is
``max(sum_k coeffs[k] * Y_k(d) + 0.5, 0)`` with ``d`` the unit direction from the camera centre to the mean.
"""

from __future__ import annotations

import torch
from torch import Tensor

# Constants of the real SH basis in the order 3DGS stores coefficients (index k = l^2 + l + m).
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per channel for an SH degree: (degree + 1)^2."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis Y_k at unit directions: dirs [..., 3] -> [..., (degree + 1)^2]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """View-dependent colour: coeffs [..., K, 3] (K >= (degree+1)^2), dirs [..., 3] (any length) -> [..., 3].

    Only the first (degree + 1)^2 coefficients are used; the result is ``clamp_min(sum + 0.5, 0)`` as in 3DGS.
    Computed in float64, returned in ``coeffs.dtype``.
    """
    k = num_sh_bases(degree)
    d = dirs.to(torch.float64)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, d)  # [..., k]
    rgb = (basis[..., :, None] * coeffs[..., :k, :].to(torch.float64)).sum(dim=-2)  # [..., 3]
    return torch.clamp_min(rgb + 0.5, 0.0).to(coeffs.dtype)
