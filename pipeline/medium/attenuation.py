"""RGB-guided attenuation (paper eq. 5) and its edge-perception network.

    A_c = exp(−w_c · β_c · (1 − γ·E(J, D)) · T · D)

per colour channel c (the printed equation's sum over c inside the exponent would make A grey, contradicting
the paper's own text on wavelength-selective attenuation; we keep one A per channel). E ∈ [0, 1] comes from a
small conv net over the rendered J and the scene-normalised depth — never the ground-truth photo, so a novel
view is rendered exactly like a training view. T is the water-type factor chosen by the classifier.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.medium.formation import MAX_EXPONENT


def rgb_guided_attenuation(D: Tensor, w: Tensor, beta: Tensor, E: Tensor, gamma: float, T: float | Tensor) -> Tensor:
    """Paper eq. 5. D [N,1,H,W] (scene units), w [3], beta [3] (≥ 0), E [N,1,H,W] in [0,1] → A [N,3,H,W] in (0,1].

    >>> A = rgb_guided_attenuation(torch.zeros(1, 1, 2, 2), torch.ones(3), torch.ones(3), torch.zeros(1, 1, 2, 2),
    ...                            0.2, 1.0)
    >>> bool((A == 1).all())
    True
    """
    coef = (w * beta).clamp(min=0).reshape(1, -1, 1, 1)
    x = coef * (1.0 - gamma * E.clamp(0, 1)) * T * D.clamp(min=0)
    return torch.exp(-x.clamp(0, MAX_EXPONENT))


class EdgePerception(nn.Module):
    """E(J, D) ∈ [0, 1]: a small conv net over [J, D/scale, |∇(D/scale)|] ending in a sigmoid. [N,1,H,W]

    Two 3×3 layers (a 5×5 receptive field: edges are local) of 4 channels, then 1×1: it runs at full
    resolution every step, so it is kept narrow (bench/medium_step.py).
    """

    def __init__(self, hidden: int = 4):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(5, hidden, 3, padding=1), nn.ReLU(),
            nn.Conv2d(hidden, hidden, 3, padding=1), nn.ReLU(),
            nn.Conv2d(hidden, 1, 1),
        )
        nn.init.constant_(self.net[-1].bias, -2.0)  # start with little modulation (E ≈ 0.12)

    def forward(self, J: Tensor, D_norm: Tensor) -> Tensor:
        gx = F.pad(D_norm[..., :, 1:] - D_norm[..., :, :-1], (0, 1, 0, 0))
        gy = F.pad(D_norm[..., 1:, :] - D_norm[..., :-1, :], (0, 0, 0, 1))
        x = torch.cat([J, D_norm, gx.abs() + gy.abs()], dim=1)
        return torch.sigmoid(self.net(x))
