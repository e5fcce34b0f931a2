"""What a training run is set up from: scene extent, target images, schedules, optimisers, initial Gaussians.

Functions of the config and the scene only (no trainer state), so each is testable on its own.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.config import TrainConfig
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.loader import load_view_image
from pipeline.scene.records import Scene, View, scaled_view
from pipeline.splat.gaussians import GAUSSIAN_KEYS, init_from_points, init_random
from pipeline.train.targets import PackedImages, pack_image

log = logging.getLogger(__name__)

ImageLike = np.ndarray | Tensor  # [H, W, 3] float in [0, 1]


def scene_extent(views: Sequence[View]) -> float:
    """1.1 x the largest distance of a camera centre from their mean (graphdeco ``getNerfppNorm``); 1.0 for
    a single camera or coincident centres. Scales the position lr and the densification size thresholds."""
    centres = np.stack([v.center for v in views])  # [V, 3]
    radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) * 1.1
    return radius if radius > 1e-6 else 1.0


def shrink_image(img: ImageLike, height: int, width: int, device: torch.device | None = None) -> Tensor:
    """``img`` [H, W, 3] area-averaged to [height, width, 3] (float32, on ``device``); the one downscale of
    training targets, whether the job loads them at the training size or the trainer shrinks them."""
    t = torch.as_tensor(img, dtype=torch.float32)
    if device is not None:
        t = t.to(device)
    if tuple(t.shape[:2]) == (height, width):
        return t
    t = F.interpolate(t.permute(2, 0, 1)[None], size=(height, width), mode="area")[0]
    return t.permute(1, 2, 0).contiguous()


def load_training_images(views: Sequence[View], downscale: int, colour_space: str = "srgb") -> PackedImages:
    """Each view's image file read one at a time, shrunk at once to the training size (``downscale``) and
    packed (:mod:`pipeline.train.targets`: uint8 when lossless, else uint16), so a survey of full-resolution
    photos never sits in memory whole (a 27 MP frame is 324 MB as float32), nor the training-size set as float:
    peak is one full-size image plus the packed set. Unpacked, exactly what :func:`prepare_images` makes of
    the full-size images when they are 8-bit at the training size; else within ``UINT16_TOLERANCE``.
    ``colour_space`` "linear": each photo decoded to linear light (sRGB EOTF) before it is averaged down
    (averaging is only physical in linear light). Item i is [h, w, 3] float32."""
    if colour_space not in ("srgb", "linear"):
        raise ValueError(f"unknown colour space {colour_space!r}")

    def shrunk():
        for view in views:
            cam = scaled_view(view, downscale).camera
            img = load_view_image(view)
            if colour_space == "linear":
                img = srgb_to_linear(img).astype(np.float32)
            yield shrink_image(img, cam.height, cam.width)

    return PackedImages.pack(shrunk())


def prepare_images(
    views: Sequence[View], images: Sequence[ImageLike], downscale: int, device: torch.device
) -> tuple[list[View], Sequence[Tensor]]:
    """Check images against their cameras and shrink both by ``downscale`` (area averaging).
    Images may also come already shrunk by an integer up to ``downscale`` (:func:`load_training_images` at the
    job's training size, which the mode probe shrinks further).
    Returns the (rescaled) views and float32 targets [H, W, 3] on ``device``: a list, or, when ``images`` are
    :class:`~pipeline.train.targets.PackedImages`, packed images again (made float one view at a time)."""
    if len(views) != len(images):
        raise ValueError(f"{len(views)} views but {len(images)} images")
    if downscale < 1:
        raise ValueError(f"downscale must be >= 1, got {downscale}")
    packed = isinstance(images, PackedImages)
    out_views, targets = [], []
    for k, view in enumerate(views):
        shape = tuple(images.packed[k].shape) if packed else tuple(np.shape(images[k]))
        small = scaled_view(view, downscale)
        # the full size, or a copy shrunk by an integer up to this downscale (the train stage loads its images at
        # the job's training size; the mode probe trains these at its own, smaller, size)
        cams = [scaled_view(view, d).camera for d in range(1, downscale + 1)]
        if shape not in {(c.height, c.width, 3) for c in cams}:
            full = (view.camera.height, view.camera.width, 3)
            raise ValueError(f"image of {view.name!r} is {shape}, camera says {full} (or a copy shrunk by an "
                             f"integer up to {downscale})")
        out_views.append(small)
        if packed and shape == (small.camera.height, small.camera.width, 3):
            targets.append(images.packed[k].to(device))  # already at the size: stays packed as it is
        elif packed:
            targets.append(pack_image(shrink_image(images[k], small.camera.height, small.camera.width)).to(device))
        else:
            targets.append(shrink_image(images[k], small.camera.height, small.camera.width, device))
    return out_views, (PackedImages(targets, device) if packed else targets)


def means_lr(cfg: TrainConfig, extent: float, iteration: int) -> float:
    """Log-linear decay from ``lr_means`` to ``lr_means_final`` over the run, times the scene extent."""
    t = min(max(iteration / max(cfg.iterations, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(cfg.lr_means) + t * math.log(cfg.lr_means_final))


def rendered_sh_degree(sh_degree: int, medium_max: int | None) -> int:
    """The highest SH degree a model renders: ``sh_degree``, capped in medium modes at the medium's limit
    (``MediumConfig.max_sh_degree``: low-order SH keeps J view-consistent); ``medium_max`` None = plain 3DGS."""
    return sh_degree if medium_max is None else min(sh_degree, medium_max)


def active_sh_degree(cfg: TrainConfig, iteration: int) -> int:
    """SH warm-up: degree 0 for the first interval, +1 per interval, capped at ``cfg.sh_degree``.
    (``iteration`` is 1-based, so iterations 1..interval-1 use degree 0, as graphdeco's loop.)"""
    return min(cfg.sh_degree, iteration // max(cfg.sh_degree_interval, 1))


def make_optimizers(params: nn.ParameterDict, cfg: TrainConfig, extent: float, *,
                    fused: bool = True) -> dict[str, torch.optim.Adam]:
    """One single-group Adam per Gaussian tensor (gsplat's strategy convention), 3DGS learning rates.

    Fused Adam (one pass over each tensor instead of one per operation): the same update to float rounding, a
    step's optimizer 9.9 → ~4.8 ms for 80k Gaussians on the CPU (docs/DECISIONS.md, "Whole-job speed");
    ``fused=False`` gives torch's for-loop Adam, its twin in tests/train/test_train.py."""
    lrs = {
        "means": cfg.lr_means * extent,
        "scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacities": cfg.lr_opacities,
        "sh0": cfg.lr_sh0,
        "shN": cfg.lr_shN,
    }
    return {
        k: torch.optim.Adam([{"params": [params[k]], "lr": lrs[k], "name": k}], eps=cfg.adam_eps, betas=(0.9, 0.999),
                            fused=fused and params[k].device.type in ("cpu", "cuda"))
        for k in GAUSSIAN_KEYS
    }


def initial_gaussians(scene: Scene, cfg: TrainConfig, extent: float, device: torch.device) -> nn.ParameterDict:
    """From the scene's points when it has more than 3, else random in a cube around the cameras."""
    kw = {"sh_degree": cfg.sh_degree, "init_opacity": cfg.init_opacity, "init_scale": cfg.init_scale}
    if len(scene.points) > 3:
        params = init_from_points(
            torch.as_tensor(scene.points, device=device), torch.as_tensor(scene.colors, device=device), **kw
        )
        log.info("initialised %d Gaussians from scene points", len(scene.points))
        return params
    centre = torch.as_tensor(np.stack([v.center for v in scene.views]).mean(0), dtype=torch.float32)
    half = cfg.random_init_extent * extent
    gen = torch.Generator().manual_seed(cfg.seed)
    params = init_random(cfg.random_init_points, centre - half, centre + half, generator=gen, **kw)
    log.info("scene has no points: %d random Gaussians in a cube of half-size %.3g", cfg.random_init_points, half)
    return params.to(device)
