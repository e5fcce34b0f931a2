"""A real lens's sharpness falling with distance, applied to a generated scene's photos.

A camera focused at ``focus`` metres blurs a surface at depth z by a circle of confusion whose diameter in pixels is
``c(z) = c∞ · |1 − focus / z|`` (thin lens, aperture and focal length folded into c∞, the blur at infinity): sharp
at the focus distance, growing towards c∞ beyond it. Here the blur is Gaussian with σ(z) = c(z) / 2, made per pixel
by blending a stack of uniformly blurred copies of the image at the two nearest σ.

This is a nuisance, not water: it changes a surface's appearance with range without changing its colour, the
case where a water model can win a held-back race for the wrong reason (contrast lost to blur imitated by a veil;
issue 39). Only the photos (``images/``) are blurred; ``clean/`` stays the sharp truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812

from pipeline.scene.images import read_image, write_image

LEVELS = 6  # blurred copies in the stack, from sharp to σ = c∞ / 2


def _gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """img [3, H, W] blurred by a separable Gaussian of std ``sigma`` pixels (edges repeated)."""
    if sigma <= 1e-3:
        return img
    r = max(1, int(np.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    p = F.pad(img[None], (r, r, r, r), mode="replicate")
    p = F.conv2d(p, k.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    p = F.conv2d(p, k.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    return p[0]


def defocus(image: np.ndarray, depth: np.ndarray, focus: float, blur_at_infinity: float) -> np.ndarray:
    """image [H, W, 3] in [0, 1]; depth [H, W] camera-space z in metres (inf where nothing is hit: blurred as at
    infinity); returns the image with per-pixel Gaussian blur σ(z) = blur_at_infinity · |1 − focus / z| / 2."""
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
    sigma = 0.5 * blur_at_infinity * np.abs(1.0 - focus / z)
    top = 0.5 * blur_at_infinity
    if top <= 1e-3:
        return image.copy()
    levels = np.linspace(0.0, top, LEVELS)
    src = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float64)).permute(2, 0, 1)
    stack = np.stack([_gaussian_blur(src, s).permute(1, 2, 0).numpy() for s in levels])  # [L, H, W, 3]
    pos = np.clip(sigma / top * (LEVELS - 1), 0, LEVELS - 1)
    lo = np.minimum(np.floor(pos).astype(int), LEVELS - 2)
    t = (pos - lo)[..., None]
    rows, cols = np.indices(z.shape)
    out = (1 - t) * stack[lo, rows, cols] + t * stack[lo + 1, rows, cols]
    return out.astype(image.dtype)


def defocus_scene(root: str | Path, blur_at_infinity: float, focus: float | None = None) -> float:
    """Blur every photo in ``root/images`` by its view's true depth (``root/depth/<stem>.npy``) with the camera
    focused at ``focus`` metres (default: the median depth over all views, where a survey camera would be set).
    Returns the focus distance used."""
    root = Path(root)
    photos = sorted(p for p in (root / "images").iterdir() if p.is_file())
    depths = {p.name: np.load(root / "depth" / f"{p.stem}.npy") for p in photos}
    if focus is None:
        finite = np.concatenate([d[np.isfinite(d)].ravel() for d in depths.values()])
        focus = float(np.median(finite))
    for p in photos:
        img = read_image(p)
        write_image(p, np.clip(np.round(defocus(img, depths[p.name], focus, blur_at_infinity) * 255), 0, 255)
                    .astype(np.uint8))
    return focus
