"""Image comparison primitives: L1, SSIM and the 3DGS loss made of them. Pure tensor functions, channel-last
images (PSNR is an evaluation metric: ``pipeline.ops.metrics``).

Images are ``[..., H, W, C]`` floats in [0, 1] (what the rasterizer returns), any leading batch shape.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.ops.ssim_cpu import ssim_planes

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = 0.01**2  # (k1 * L)^2 with L = 1
_C2 = 0.03**2


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape or a.dim() < 3:
        raise ValueError(f"images must be [..., H, W, C] of equal shape, got {tuple(a.shape)} and {tuple(b.shape)}")


def l1(a: Tensor, b: Tensor) -> Tensor:
    """Mean absolute difference. [..., H, W, C] x2 -> []"""
    _check_pair(a, b)
    return (a - b).abs().mean()


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, *, like: Tensor) -> Tensor:
    """Normalised 1-D Gaussian, on ``like``'s device and dtype. [size]"""
    x = torch.arange(size, device=like.device, dtype=like.dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _blur(x: Tensor, g: Tensor) -> Tensor:
    """Separable Gaussian filter with zero padding ('same' size). x: [B, C, H, W], g: [S] -> [B, C, H, W]"""
    c, s = x.shape[1], g.shape[0]
    x = F.conv2d(x, g.reshape(1, 1, s, 1).expand(c, 1, s, 1), padding=(s // 2, 0), groups=c)
    return F.conv2d(x, g.reshape(1, 1, 1, s).expand(c, 1, 1, s), padding=(0, s // 2), groups=c)


def ssim_map(a: Tensor, b: Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """Per-pixel SSIM (Wang et al. 2004) with a ``window``x``window`` Gaussian window (sigma 1.5),
    zero-padded borders exactly as graphdeco's ``ssim`` (a 2-D outer-product window is separable, so two
    1-D passes give the same numbers). [..., H, W, C] x2 -> [..., H, W, C]
    """
    _check_pair(a, b)
    lead, (h, w, c) = a.shape[:-3], a.shape[-3:]
    x = a.reshape(-1, h, w, c).permute(0, 3, 1, 2)  # [B, C, H, W]
    y = b.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    g = gaussian_window_1d(window, sigma, like=x)
    mu_x, mu_y = _blur(x, g), _blur(y, g)
    sxx = _blur(x * x, g) - mu_x**2
    syy = _blur(y * y, g) - mu_y**2
    sxy = _blur(x * y, g) - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * sxy + _C2)
    den = (mu_x**2 + mu_y**2 + _C1) * (sxx + syy + _C2)
    return (num / den).permute(0, 2, 3, 1).reshape(*lead, h, w, c)


def ssim(a: Tensor, b: Tensor) -> Tensor:
    """Mean SSIM over pixels, channels and batch. [..., H, W, C] x2 -> []

    float32 CPU images whose second one needs no gradient (a render against its target) go through
    :func:`pipeline.ops.ssim_cpu.ssim_planes` (numba, ~5x faster forward and backward); everything else, and
    the tests' reference, through the torch twin :func:`ssim_map`."""
    _check_pair(a, b)
    if a.device.type != "cpu" or a.dtype != torch.float32 or b.dtype != torch.float32 or b.requires_grad:
        return ssim_map(a, b).mean()
    return ssim_planes(_planes(a), _planes(b), gaussian_window_1d(like=a), _C1, _C2)


def _planes(x: Tensor) -> Tensor:
    """[..., H, W, C] -> [B*C, H, W], one plane per channel of every image (a view when x is channels-first
    underneath, as the medium's NCHW renders are)."""
    h, w, c = x.shape[-3:]
    return x.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, h, w)


def photometric_losses(render: Tensor, target: Tensor, ssim_weight: float, *,
                       channels_first: bool = False) -> dict[str, Tensor]:
    """The 3DGS photometric loss as named, already-weighted terms (sum them once): (1 − w)·L1 and w·(1 − SSIM).
    Each caller keeps its own w (``TrainConfig.ssim_weight`` before the medium starts, ``LossWeights.ssim_weight``
    in eq. 13's L_basic). [..., H, W, C] x2, or [N, C, H, W] x2 with ``channels_first`` -> {"l1": [], "dssim": []}"""
    hwc = (lambda x: x.permute(0, 2, 3, 1)) if channels_first else (lambda x: x)
    # SSIM before L1: the order the autograd graph records them in is the order their gradients are added into
    # ``render``, and a run is repeated bit for bit only in the same order
    dssim = ssim_weight * (1.0 - ssim(hwc(render), hwc(target)))
    return {"l1": (1.0 - ssim_weight) * l1(render, target), "dssim": dssim}
