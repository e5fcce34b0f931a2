"""The medium as a module: the water between the camera and the splatted scene.

Modes (``TrainConfig.mode``; ``MediumConfig`` holds the medium's settings):
- ``3dgs``: no medium, I = J (composited over the background colour by the rasterizer).
- ``homogeneous``: one global per-channel β_D, β_B, B∞ (eq. 3), the medium of SeaThru-style methods.
- ``dualphys``: eq. 5 attenuation and eq. 8 backscatter, each module switchable for the ablation table.

The module sees only rendered quantities of the view being rendered: J (alpha-premultiplied radiance), the
alpha-normalised depth converted to distance along the ray, and alpha. Its parameters live in their own
optimizer so densification never touches them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.config import MediumConfig
from pipeline.medium.attenuation import EdgePerception, rgb_guided_attenuation
from pipeline.medium.formation import composite_over_water, homogeneous_backscatter, transmission
from pipeline.medium.scattering import MultiScaleFeatures, depth_confidence, depth_edge_factor, multiscale_backscatter


@dataclass
class MediumOutput:
    """Everything one view's medium produces. All [N, C, H, W]."""

    I: Tensor  # noqa: E741  with-water image, 3 channels
    A: Tensor  # direct transmission (attenuation map), 3 channels, in (0, 1]
    B: Tensor  # backscatter at the surface depth, 3 channels
    B_frac: Tensor  # backscatter fraction B / B∞ ∈ [0, 1), 3 channels (the paper's B_s)
    beta_eff: Tensor  # [3] the image's mean effective attenuation coefficient (w·β·(1 − γE)·T), 1/scene-unit


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


class Medium(nn.Module):
    """Water model for ``homogeneous`` and ``dualphys`` modes.

    Args:
        mode: "homogeneous" or "dualphys".
        rgb_attenuation / multiscale_scattering: the dualphys modules (ablation switches); off → that path is
            homogeneous.
        gamma, lam, delta: modulation strengths of eqs. 5 and 8.
        depth_scale: the scene's depth normaliser (e.g. median SfM depth), fixed once per scene; only the
            networks' inputs are divided by it, the physics uses D in scene units.
        init_beta / init_binf / init_beta_b: starting coefficients (per channel), from the sparse-point estimate
            or the classifier's water type; β_B starts at β_D unless given.
    """

    def __init__(self, mode: str = "dualphys", *, rgb_attenuation: bool = True, multiscale_scattering: bool = True,
                 gamma: float = 0.3, lam: float = 0.3, delta: float = 0.5, depth_scale: float = 1.0,
                 init_beta: tuple[float, float, float] = (0.3, 0.15, 0.1),
                 init_binf: tuple[float, float, float] = (0.1, 0.3, 0.4),
                 init_beta_b: tuple[float, float, float] | None = None):
        super().__init__()
        if mode not in ("homogeneous", "dualphys"):
            raise ValueError(f"Medium mode must be 'homogeneous' or 'dualphys', got {mode!r}")
        self.mode = mode
        self.rgb_attenuation = mode == "dualphys" and rgb_attenuation
        self.multiscale_scattering = mode == "dualphys" and multiscale_scattering
        self.gamma, self.lam, self.delta = gamma, lam, delta
        self.register_buffer("depth_scale", torch.tensor(float(depth_scale)))
        self.register_buffer("water_factor", torch.tensor(1.0))  # T of eq. 5, set by the controller
        self.beta_d_raw = nn.Parameter(torch.tensor([_inv_softplus(b) for b in init_beta]))
        self.beta_b_raw = nn.Parameter(torch.tensor([_inv_softplus(b) for b in (init_beta_b or init_beta)]))
        self.binf_raw = nn.Parameter(torch.tensor([_logit(b) for b in init_binf]))
        self.w = nn.Parameter(torch.ones(3))  # eq. 5's wavelength weights (fixed at 1 when homogeneous)
        self.w.requires_grad_(mode == "dualphys")
        self.edge = EdgePerception() if self.rgb_attenuation else None
        self.multiscale = MultiScaleFeatures() if self.multiscale_scattering else None

    @classmethod
    def from_config(cls, mode: str, cfg: MediumConfig, depth_scale: float, **init: Any) -> Medium:
        """The medium ``cfg`` describes (modules, modulation strengths) for a scene with this depth normaliser;
        ``init``: the starting coefficients (``init_beta``, ``init_binf``, ``init_beta_b``), else the defaults."""
        return cls(mode, rgb_attenuation=cfg.rgb_attenuation, multiscale_scattering=cfg.multiscale_scattering,
                   gamma=cfg.gamma, lam=cfg.lam, delta=cfg.delta, depth_scale=depth_scale, **init)

    @property
    def beta_D(self) -> Tensor:  # [3] 1/scene-unit
        return F.softplus(self.beta_d_raw)

    @property
    def beta_B(self) -> Tensor:  # [3]
        return F.softplus(self.beta_b_raw)

    @property
    def B_inf(self) -> Tensor:  # [3] in (0, 1)
        return torch.sigmoid(self.binf_raw)

    def attenuation(self, J: Tensor, D: Tensor) -> tuple[Tensor, Tensor]:
        """(A [N,3,H,W], mean effective coefficient [3]): eq. 5 when RGB-guided, else exp(−β_D·D)."""
        coef = self.w * self.beta_D
        if self.edge is None:
            return transmission(coef, D), coef
        E = self.edge(J, D / self.depth_scale)
        A = rgb_guided_attenuation(D, self.w, self.beta_D, E, self.gamma, self.water_factor)
        return A, coef * (1.0 - self.gamma * E.clamp(0, 1).mean()) * self.water_factor

    def backscatter(self, D: Tensor) -> Tensor:
        """B [N,3,H,W]: eq. 8 when multi-scale, else eq. 6."""
        if self.multiscale is None:
            return homogeneous_backscatter(D, self.beta_B, self.B_inf)
        M = self.multiscale(D / self.depth_scale)
        return multiscale_backscatter(D, self.beta_B, self.B_inf, depth_confidence(D), depth_edge_factor(D), M,
                                      self.lam, self.delta)

    def forward(self, J: Tensor, D: Tensor, alpha: Tensor | None = None) -> MediumOutput:
        """J [N,3,H,W] rendered (premultiplied) radiance; D [N,1,H,W] distance along the ray; alpha [N,1,H,W].

        I is eq. 4 over the water (:func:`~pipeline.medium.formation.composite_over_water`): J·A + alpha·B where
        the Gaussians cover the pixel, the veiling light B∞ where they do not (no alpha: fully covered)."""
        if J.ndim != 4 or J.shape[1] != 3 or D.shape != (J.shape[0], 1, *J.shape[2:]):
            raise ValueError(f"expected J [N,3,H,W] and D [N,1,H,W], got {tuple(J.shape)} and {tuple(D.shape)}")
        A, beta_eff = self.attenuation(J, D)
        B = self.backscatter(D)
        binf = self.B_inf
        if alpha is None:
            alpha = torch.ones_like(D)
        I = composite_over_water(J, A, B, alpha, binf)  # noqa: E741
        return MediumOutput(I=I, A=A, B=B, B_frac=B / binf.reshape(1, -1, 1, 1), beta_eff=beta_eff)
