"""Random Gaussian clouds in front of a pinhole camera: the rasterizer's test and benchmark scene.

The scene the cpu backend was chosen on: N Gaussians in a 3.2 x 2.4 x 2 volume 3 to 5 units in front of a camera
with a 53 degree horizontal field of view; log-normal scales shrinking as N^(-1/3), the way densification makes
Gaussians smaller. The base scale 0.022 * (50k / N)^(1/3) reproduces that measurement's load of Gaussians per
pixel (docs/DECISIONS.md, "Numbers behind code comments").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class RandomScene:
    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3], or SH coefficients [N, 16, 3] with sh=True
    viewmats: Tensor  # [1, 4, 4]
    Ks: Tensor  # [1, 3, 3]
    width: int
    height: int

    def params(self) -> list[Tensor]:
        """The five learnable inputs, in rasterize's argument order."""
        return [self.means, self.quats, self.scales, self.opacities, self.colors]


def pinhole_K(width: int, height: int, hfov_deg: float = 53.0) -> Tensor:
    """[3, 3] intrinsics with the principal point at the image centre (COLMAP pixel-centre convention)."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def random_scene(
    n: int,
    width: int,
    height: int,
    *,
    seed: int = 0,
    opacity: tuple[float, float] = (0.05, 0.95),
    sh: bool = False,
) -> RandomScene:
    """The notes' benchmark scene with a camera at the origin looking down +z (opacities uniform in ``opacity``)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([3.2, 2.4, 2.0]) + torch.tensor([-1.6, -1.2, 3.0])
    quats = torch.randn(n, 4, generator=g)
    base = 0.022 * (50000 / max(n, 1)) ** (1 / 3)
    scales = base * torch.exp(0.5 * torch.randn(n, 3, generator=g))
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    if sh:
        colors = 0.3 * torch.randn(n, 16, 3, generator=g)
    else:
        colors = torch.rand(n, 3, generator=g)
    return RandomScene(
        means, quats, scales, opacities, colors, torch.eye(4)[None], pinhole_K(width, height)[None], width, height
    )
