"""Pooled image statistics that the water-type classifier reads (pure functions, tensors in and out).

The paper's classifier (eq. 14) is ``Softmax(W2 · ReLU(W1 · AvgPool(I_RGB)))``. Plain average pooling of the RGB
image keeps only the mean colour, which cannot tell a near, turbid scene from a far, clear one. We pool a few
per-pixel quantities with the physical meaning the paper names for its feature networks (§4, "blue-green
channel ratios, edge gradients, and colour saturation distributions") into a fixed-length vector; the MLP of
eq. 14 runs on that vector (:mod:`.classifier`).

Images are first area-resized so the short side is :data:`FEATURE_SHORT_SIDE` pixels: gradient and patch
statistics then mean the same thing for a 64×48 synthetic frame and a 256×256 photo.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

FEATURE_SHORT_SIDE = 48  # pixels; short side of the image the statistics are computed on
DARK_PATCH = 3  # pixels (at FEATURE_SHORT_SIDE); min-filter size of the dark / max-filter of the bright channel
EPS = 1e-3  # guards ratios of near-black channels (1/4 of an 8-bit step)
LUMA = (0.299, 0.587, 0.114)  # Rec. 601 weights
VEIL_FRACTION = 0.1  # share of pixels with the highest dark channel whose colour estimates the veil B∞

FEATURE_NAMES: tuple[str, ...] = (
    "mean_r", "mean_g", "mean_b",
    "std_r", "std_g", "std_b",
    "log_bg_ratio",  # log((mean_b + eps) / (mean_g + eps))
    "log_rg_ratio",  # log((mean_r + eps) / (mean_g + eps))
    "dark_channel_mean",  # mean over pixels of the patch-min of the per-pixel channel min
    "bright_channel_mean",  # mean over pixels of the patch-max of the per-pixel channel max
    "rms_contrast",  # std(Y) / mean(Y)
    "gradient_contrast",  # mean |∇Y| / mean(Y), gradients in pixels of the resized image
    "saturation_mean", "saturation_std",  # HSV saturation (max − min) / max
    "luma_q05", "luma_q50", "luma_q95",
    "q95_r", "q95_g", "q95_b",
    "q05_r", "q05_g", "q05_b",  # the floor of each channel: backscatter where the scene is dark or far
    "cv_r", "cv_g", "cv_b",  # std / mean per channel: how much of each channel is scene rather than veil
    "veil_log_bg", "veil_log_rg",  # colour of the haziest pixels (top VEIL_FRACTION of the dark channel)
)
NUM_FEATURES = len(FEATURE_NAMES)


def resize_short_side(images: Tensor, short_side: int = FEATURE_SHORT_SIDE) -> Tensor:
    """Area-resize [N, 3, H, W] so that min(H, W) == short_side (aspect kept). → [N, 3, H', W']"""
    _check(images)
    h, w = images.shape[-2:]
    s = short_side / min(h, w)
    size = (max(1, round(h * s)), max(1, round(w * s)))
    if size == (h, w):
        return images
    return F.interpolate(images, size=size, mode="area")


def dark_channel(images: Tensor, patch: int = DARK_PATCH) -> Tensor:
    """He et al.'s dark channel: per-pixel min over RGB, then a min filter of ``patch`` pixels. [N,3,H,W] → [N,H,W]

    >>> img = torch.tensor([0.2, 0.5, 0.7]).reshape(1, 3, 1, 1).expand(1, 3, 4, 4)
    >>> bool(torch.allclose(dark_channel(img), torch.full((1, 4, 4), 0.2)))
    True
    """
    _check(images)
    m = images.amin(dim=1, keepdim=True)  # [N, 1, H, W]
    # Replicate padding so the border is not pulled towards a fake value.
    p = patch // 2
    m = F.pad(m, (p, p, p, p), mode="replicate")
    return -F.max_pool2d(-m, patch, stride=1)[:, 0]


def bright_channel(images: Tensor, patch: int = DARK_PATCH) -> Tensor:
    """Per-pixel max over RGB, then a max filter of ``patch`` pixels. [N,3,H,W] → [N,H,W]"""
    _check(images)
    m = images.amax(dim=1, keepdim=True)
    p = patch // 2
    m = F.pad(m, (p, p, p, p), mode="replicate")
    return F.max_pool2d(m, patch, stride=1)[:, 0]


def luma(images: Tensor) -> Tensor:
    """Rec. 601 luma. [N,3,H,W] → [N,H,W]"""
    _check(images)
    w = images.new_tensor(LUMA).reshape(1, 3, 1, 1)
    return (images * w).sum(dim=1)


def saturation(images: Tensor) -> Tensor:
    """HSV saturation (max − min) / max, 0 for black pixels. [N,3,H,W] → [N,H,W]"""
    _check(images)
    mx, mn = images.amax(dim=1), images.amin(dim=1)
    return torch.where(mx > EPS, (mx - mn) / mx.clamp(min=EPS), torch.zeros_like(mx))


def gradient_magnitude(y: Tensor) -> Tensor:
    """Forward-difference gradient magnitude of [N,H,W], cropped to [N,H-1,W-1]."""
    gx = y[:, :-1, 1:] - y[:, :-1, :-1]
    gy = y[:, 1:, :-1] - y[:, :-1, :-1]
    return torch.sqrt(gx * gx + gy * gy)


def blue_green_ratio(images: Tensor) -> Tensor:
    """Ratio of the image means of blue and green, (mean_b + eps) / (mean_g + eps). [N,3,H,W] → [N]

    >>> img = torch.tensor([0.0, 0.25, 0.5]).reshape(1, 3, 1, 1).expand(1, 3, 2, 2)
    >>> round(float(blue_green_ratio(img)[0]), 3)
    1.996
    """
    _check(images)
    m = images.mean(dim=(2, 3))
    return (m[:, 2] + EPS) / (m[:, 1] + EPS)


def veil_colour(images: Tensor, fraction: float = VEIL_FRACTION) -> Tensor:
    """Mean colour of the ``fraction`` of pixels with the highest dark channel. [N,3,H,W] → [N, 3]

    He et al.'s estimate of the airlight: where the dark channel is brightest, the pixel is mostly veil (far
    range or dark scene), so its colour approaches B∞.

    >>> img = torch.tensor([0.1, 0.3, 0.4]).reshape(1, 3, 1, 1).expand(1, 3, 5, 5)
    >>> [round(v, 3) for v in veil_colour(img)[0].tolist()]
    [0.1, 0.3, 0.4]
    """
    _check(images)
    n = images.shape[0]
    dark = dark_channel(images).reshape(n, -1)  # [N, P]
    k = max(1, round(fraction * dark.shape[1]))
    idx = dark.topk(k, dim=1).indices  # [N, k]
    px = images.reshape(n, 3, -1).gather(2, idx[:, None, :].expand(n, 3, k))  # [N, 3, k]
    return px.mean(dim=2)


def image_features(images: Tensor, *, resize: bool = True) -> Tensor:
    """The classifier's input vector, named by :data:`FEATURE_NAMES`. [N, 3, H, W] in [0, 1] → [N, NUM_FEATURES]

    ``resize=False`` skips the area resize (for hand-checked values on tiny arrays); the classifier always
    resizes, so a photo and a small synthetic frame are compared at the same scale.
    """
    _check(images)
    x = resize_short_side(images) if resize else images
    x = x.clamp(0.0, 1.0)
    n = x.shape[0]
    flat = x.reshape(n, 3, -1)  # [N, 3, P]
    mean = flat.mean(dim=2)  # [N, 3]
    std = flat.std(dim=2, correction=0)
    log_bg = torch.log((mean[:, 2] + EPS) / (mean[:, 1] + EPS))
    log_rg = torch.log((mean[:, 0] + EPS) / (mean[:, 1] + EPS))
    dark = dark_channel(x).reshape(n, -1).mean(dim=1)
    bright = bright_channel(x).reshape(n, -1).mean(dim=1)
    y = luma(x)  # [N, H, W]
    y_flat = y.reshape(n, -1)
    y_mean = y_flat.mean(dim=1)
    rms = y_flat.std(dim=1, correction=0) / (y_mean + EPS)
    if min(y.shape[-2:]) > 1:
        grad = gradient_magnitude(y).reshape(n, -1).mean(dim=1) / (y_mean + EPS)
    else:
        grad = torch.zeros_like(y_mean)
    sat = saturation(x).reshape(n, -1)
    qs = x.new_tensor([0.05, 0.5, 0.95])
    y_q = torch.quantile(y_flat, qs, dim=1).T  # [N, 3]
    c_q = torch.quantile(flat, qs[[2, 0]], dim=2)  # [2, N, 3]: 95 % and 5 % per channel
    cv = std / (mean + EPS)
    veil = veil_colour(x)  # [N, 3]
    veil_bg = torch.log((veil[:, 2] + EPS) / (veil[:, 1] + EPS))
    veil_rg = torch.log((veil[:, 0] + EPS) / (veil[:, 1] + EPS))
    feats = torch.cat([
        mean, std, log_bg[:, None], log_rg[:, None], dark[:, None], bright[:, None], rms[:, None], grad[:, None],
        sat.mean(dim=1, keepdim=True), sat.std(dim=1, correction=0, keepdim=True), y_q, c_q[0], c_q[1], cv,
        veil_bg[:, None], veil_rg[:, None],
    ], dim=1)
    return feats  # [N, NUM_FEATURES]


def _check(images: Tensor) -> None:
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[-1] < 1 or images.shape[-2] < 1:
        raise ValueError(f"expected images [N, 3, H, W], got {tuple(images.shape)}")
