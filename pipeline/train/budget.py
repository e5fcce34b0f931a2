"""The Gaussian budget and the SH degree a scene needs (``--mode auto``), from its view count and resolution.

- Gaussians: published 3DGS runs end with about 0.02-0.03 Gaussians per training pixel (Mip-NeRF 360 garden:
  ~5.8M for 185 views of ~1.1 Mpx; Tanks and Temples truck: ~2.5M for 251 views of ~0.5 Mpx). The budget is
  ``GAUSSIANS_PER_PIXEL`` (about twice that) times the training pixels, so it binds only when growth runs
  away, clamped to [``MIN_GAUSSIANS``, the preset's cap] (``MAX_GAUSSIANS`` when the preset has none).
- SH degree: degree d adds (d + 1)² colour coefficients per channel that only views from different directions
  can pin down; with few views the higher bands fit noise and the held-out views pay for it. Degree 1 below
  ``SH_VIEWS[0]`` views, 2 below ``SH_VIEWS[1]``, else 3 (the 3DGS default). Images narrower than
  ``SH_MIN_WIDTH`` keep at most degree 1: view-dependent detail there is below a pixel.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

GAUSSIANS_PER_PIXEL = 0.05
MIN_GAUSSIANS = 10_000
MAX_GAUSSIANS = 3_000_000
SH_VIEWS = (30, 80)
SH_MIN_WIDTH = 200


@dataclass(frozen=True)
class SceneBudget:
    max_gaussians: int  # densification cap
    sh_degree: int  # maximum spherical-harmonics degree
    training_pixels: int  # views x width x height at the training resolution

    def to_json(self) -> dict:
        return asdict(self)


def pixel_budget(pixels: int) -> int:
    """``GAUSSIANS_PER_PIXEL`` x ``pixels`` (training pixels), before any clamp."""
    return round(GAUSSIANS_PER_PIXEL * pixels)


def scene_budget(n_views: int, width: int, height: int, preset_cap: int = 0, preset_sh: int = 3) -> SceneBudget:
    """Budget for ``n_views`` training images of ``width`` x ``height`` (training resolution), never above the
    preset's cap (0 = none) or SH degree."""
    if n_views < 1 or width < 1 or height < 1:
        raise ValueError(f"scene_budget needs a positive view count and size, got {n_views} x {width}x{height}")
    pixels = n_views * width * height
    cap = preset_cap if preset_cap > 0 else MAX_GAUSSIANS
    gaussians = min(cap, max(MIN_GAUSSIANS, pixel_budget(pixels)))
    sh = 1 if n_views < SH_VIEWS[0] else 2 if n_views < SH_VIEWS[1] else 3
    if width < SH_MIN_WIDTH:
        sh = min(sh, 1)
    return SceneBudget(max_gaussians=int(gaussians), sh_degree=min(sh, preset_sh), training_pixels=pixels)


__all__ = ["SceneBudget", "pixel_budget", "scene_budget"]
