"""Gaussian parameters: a named ``nn.ParameterDict``, its activations and its initialisation.

The dict holds only per-Gaussian tensors (one row per Gaussian), stored unconstrained:

    means     [N, 3]      world xyz
    scales    [N, 3]      log of the standard deviations
    quats     [N, 4]      rotation, wxyz, unnormalised
    opacities [N]         logit of the opacity
    sh0       [N, 1, 3]   SH DC coefficient per colour channel
    shN       [N, K-1, 3] higher SH bands, K = (degree + 1)^2 (15 for degree 3)

That is exactly what ``gsplat.strategy`` grows and prunes. Anything that is not per-Gaussian (the medium
networks of DualPhys) lives in its own module and optimiser, so the strategy never sees it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))
GAUSSIAN_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel up to ``degree``: (degree + 1)^2."""
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Colour in [0, 1] to the SH DC coefficient that renders it (3DGS: colour = C0 * SH + 0.5). [..., 3]"""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of ``rgb_to_sh0``. [..., 3]"""
    return sh0 * SH_C0 + 0.5


def check_gaussians(params: nn.ParameterDict | dict[str, Tensor]) -> int:
    """Validate key set and shapes; return N. Raises ``ValueError`` naming the offending shape."""
    missing = [k for k in GAUSSIAN_KEYS if k not in params]
    if missing:
        raise ValueError(f"Gaussian parameters lack {missing}; got keys {sorted(params)}")
    n = params["means"].shape[0]
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3)}
    for key, shape in expected.items():
        if tuple(params[key].shape) != shape:
            raise ValueError(f"{key} must have shape {shape}, got {tuple(params[key].shape)}")
    shn = params["shN"]
    k = shn.shape[1] + 1 if shn.dim() == 3 else -1
    if shn.dim() != 3 or shn.shape[0] != n or shn.shape[2] != 3 or round(math.sqrt(k)) ** 2 != k:
        raise ValueError(f"shN must have shape ({n}, (d+1)^2 - 1, 3), got {tuple(shn.shape)}")
    return n


def sh_degree_of(params: nn.ParameterDict | dict[str, Tensor]) -> int:
    """The SH degree the parameters can represent (from the shape of shN)."""
    return round(math.sqrt(params["shN"].shape[1] + 1)) - 1


@dataclass
class ActivatedGaussians:
    """Constrained values, what a rasterizer takes."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] wxyz, unnormalised
    scales: Tensor  # [N, 3] standard deviations (> 0)
    opacities: Tensor  # [N] in (0, 1)
    sh0: Tensor  # [N, 1, 3] SH DC coefficient
    shN: Tensor  # [N, K - 1, 3] higher SH bands

    @property
    def sh(self) -> Tensor:
        """All SH coefficients, DC first [N, K, 3] (a concatenation: the rasterizer takes sh0 and shN apart)."""
        return torch.cat([self.sh0, self.shN], dim=1)


def activate(params: nn.ParameterDict | dict[str, Tensor]) -> ActivatedGaussians:
    """exp for scales, sigmoid for opacities; the SH bands as they are. Differentiable."""
    return ActivatedGaussians(
        means=params["means"],
        quats=params["quats"],
        scales=torch.exp(params["scales"]),
        opacities=torch.sigmoid(params["opacities"]),
        sh0=params["sh0"],
        shN=params["shN"],
    )


def make_gaussians(
    means: Tensor,  # [N, 3]
    log_scales: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    logit_opacities: Tensor,  # [N]
    sh0: Tensor,  # [N, 1, 3]
    shN: Tensor,  # [N, K-1, 3]
) -> nn.ParameterDict:
    """Wrap raw tensors as trainable float32 parameters (copies), validating shapes."""
    raw = {
        "means": means,
        "scales": log_scales,
        "quats": quats,
        "opacities": logit_opacities,
        "sh0": sh0,
        "shN": shN,
    }
    check_gaussians(raw)
    return nn.ParameterDict({k: nn.Parameter(raw[k].detach().to(torch.float32).clone()) for k in GAUSSIAN_KEYS})


def knn_rms_distance(points: Tensor, k: int = 3, max_block_elems: int = 1 << 22) -> Tensor:
    """Root-mean-square distance from each point to its ``k`` nearest other points. [P, 3] -> [P]

    This is what graphdeco's ``distCUDA2`` computes (mean of the squared distances to the 3 nearest
    neighbours; 3DGS initialises each scale to its square root). Brute force in row blocks of at most
    ``max_block_elems`` distances, so memory stays bounded (O(P^2) time: fine for SfM clouds of ~1e5).
    Neighbour search uses the fast matmul form; the chosen neighbours' distances are then recomputed
    exactly from coordinate differences.
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [P, 3], got {tuple(points.shape)}")
    p = points.shape[0]
    if p <= k:
        raise ValueError(f"need more than k={k} points for a kNN scale, got {p}")
    pts = points.detach().to(torch.float32)
    block = max(1, max_block_elems // p)
    out = torch.empty(p, dtype=torch.float32, device=points.device)
    for start in range(0, p, block):
        q = pts[start : start + block]  # [B, 3]
        d2 = torch.cdist(q, pts).square_()  # [B, P] (approximate; only used for selection)
        rows = torch.arange(q.shape[0], device=points.device)
        d2[rows, rows + start] = float("inf")  # exclude the point itself, not its duplicates
        idx = d2.topk(k, dim=1, largest=False).indices  # [B, k]
        exact = (pts[idx] - q[:, None, :]).square().sum(-1)  # [B, k]
        out[start : start + block] = exact.mean(-1).clamp_min(1e-7).sqrt()
    return out


def _gaussians_at(
    means: Tensor,  # [N, 3]
    rgb: Tensor,  # [N, 3] in [0, 1]
    *,
    sh_degree: int,
    init_opacity: float,
    init_scale: float,
) -> nn.ParameterDict:
    n = means.shape[0]
    scales = torch.log(knn_rms_distance(means) * init_scale)[:, None].repeat(1, 3)  # [N, 3]
    quats = torch.zeros(n, 4, device=means.device)
    quats[:, 0] = 1.0  # identity rotation, w first
    opac = torch.full((n,), math.log(init_opacity / (1.0 - init_opacity)), device=means.device)
    sh0 = rgb_to_sh0(rgb.to(torch.float32))[:, None, :]  # [N, 1, 3]
    shn = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=means.device)
    return make_gaussians(means, scales, quats, opac, sh0, shn)


def init_from_points(
    points: Tensor | np.ndarray,  # [P, 3]
    colors: Tensor | np.ndarray,  # [P, 3] in [0, 1]
    *,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    init_scale: float = 1.0,
) -> nn.ParameterDict:
    """3DGS initialisation from an SfM cloud: one isotropic Gaussian per point, coloured by its SH DC,
    scale = kNN RMS distance (k = 3), opacity ``init_opacity``, identity rotation."""
    pts = torch.as_tensor(points, dtype=torch.float32)
    cols = torch.as_tensor(colors, dtype=torch.float32, device=pts.device)
    if pts.dim() != 2 or pts.shape[1] != 3 or cols.shape != pts.shape:
        raise ValueError(f"points and colors must both be [P, 3], got {tuple(pts.shape)} and {tuple(cols.shape)}")
    return _gaussians_at(pts, cols, sh_degree=sh_degree, init_opacity=init_opacity, init_scale=init_scale)


def init_random(
    n: int,
    lo: Tensor | np.ndarray,  # [3] box minimum
    hi: Tensor | np.ndarray,  # [3] box maximum
    *,
    generator: torch.Generator | None = None,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    init_scale: float = 1.0,
) -> nn.ParameterDict:
    """``n`` Gaussians uniform in the box [lo, hi] with uniform random colours (when there is no SfM cloud).

    Means, then colours, are drawn from ``generator``; scales follow from the kNN distances."""
    lo_t = torch.as_tensor(lo, dtype=torch.float32).reshape(3)
    hi_t = torch.as_tensor(hi, dtype=torch.float32, device=lo_t.device).reshape(3)
    if not bool((hi_t > lo_t).all()):
        raise ValueError(f"empty box: lo={lo_t.tolist()} hi={hi_t.tolist()}")
    u = torch.rand(n, 6, generator=generator, device=lo_t.device)  # [N, 6]
    means = lo_t + u[:, :3] * (hi_t - lo_t)
    return _gaussians_at(means, u[:, 3:], sh_degree=sh_degree, init_opacity=init_opacity, init_scale=init_scale)
