"""LPIPS-VGG (Zhang et al., CVPR 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric"), in plain torch, loaded only from a local weights file.

The network is the ``lpips`` package's v0.1 VGG variant, the one 3DGS reports: inputs in [-1, 1] are shifted
and scaled per channel, passed through VGG-16's convolutional trunk, and at relu1_2, relu2_2, relu3_3, relu4_3
and relu5_3 the features are unit-normalised over channels, differenced, squared, weighted per channel by a
1x1 convolution (no bias), averaged over the image and summed over the five layers.

Weights are never downloaded. ``DUALPHYS_LPIPS_WEIGHTS`` names a ``.pth`` in the standard layouts:

- a whole LPIPS state dict (``net.slice1.0.weight`` ... and ``lin0.model.1.weight`` ...), or
- the ``lpips`` package's ``weights/v0.1/vgg.pth`` (only ``lin0..lin4``), with ``DUALPHYS_LPIPS_BACKBONE``
  naming torchvision's VGG-16 ImageNet weights (``vgg16-397923af.pth``, keys ``features.N.weight``).

Without them the evaluation reports LPIPS as ``null`` with the reason (never a stand-in network).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

WEIGHTS_ENV = "DUALPHYS_LPIPS_WEIGHTS"
BACKBONE_ENV = "DUALPHYS_LPIPS_BACKBONE"

# VGG-16 "D" trunk: channel counts, "M" = 2x2 max pool. Indices in torchvision's ``features`` follow from it.
_VGG16 = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
# The lpips package's slices of ``features``: [0, 4) -> relu1_2, [4, 9) -> relu2_2, ... [23, 30) -> relu5_3.
_SLICE_ENDS = (4, 9, 16, 23, 30)
LAYER_CHANNELS = (64, 128, 256, 512, 512)
_SHIFT = (-0.030, -0.088, -0.188)  # lpips ScalingLayer
_SCALE = (0.458, 0.448, 0.450)


class LPIPSUnavailable(RuntimeError):
    """No usable local weights; the message is the reason the report gives."""


def _vgg_trunk() -> nn.Sequential:
    """torchvision's ``vgg16().features[:30]`` layer for layer (same indices, so its keys load unchanged)."""
    layers: list[nn.Module] = []
    c_in = 3
    for v in _VGG16:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, int(v), 3, padding=1), nn.ReLU()]
            c_in = int(v)
    return nn.Sequential(*layers)


class LPIPSVGG(nn.Module):
    """LPIPS distance with the VGG-16 trunk. ``forward(a, b)``: [B, 3, H, W] in [0, 1] x2 -> [B]."""

    def __init__(self) -> None:
        super().__init__()
        self.features = _vgg_trunk()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in LAYER_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).reshape(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).reshape(1, 3, 1, 1))

    def taps(self, x: Tensor) -> list[Tensor]:
        """Unit-normalised features at the five relu taps. [B, 3, H, W] in [0, 1] -> 5 x [B, C_l, H_l, W_l]"""
        x = ((2 * x - 1) - self.shift) / self.scale
        out, start = [], 0
        for end in _SLICE_ENDS:
            for layer in self.features[start:end]:
                x = layer(x)
            out.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
            start = end
        return out

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        if a.shape != b.shape or a.dim() != 4 or a.shape[1] != 3:
            raise ValueError(f"LPIPS expects two [B, 3, H, W] images, got {tuple(a.shape)} and {tuple(b.shape)}")
        total = torch.zeros(a.shape[0], dtype=a.dtype, device=a.device)
        for lin, fa, fb in zip(self.lins, self.taps(a), self.taps(b), strict=True):
            total = total + lin((fa - fb) ** 2).mean(dim=(1, 2, 3))
        return total


def _trunk_keys(sd: dict[str, Tensor], prefix_re: str) -> dict[str, Tensor]:
    """``features.N.*`` keys from a state dict whose trunk keys match ``prefix_re`` + ``N.(weight|bias)``."""
    out = {}
    for k, v in sd.items():
        m = re.fullmatch(prefix_re + r"(\d+)\.(weight|bias)", k)
        if m and int(m.group(1)) < _SLICE_ENDS[-1]:
            out[f"{m.group(1)}.{m.group(2)}"] = v
    return out


def _load(path: Path) -> dict[str, Tensor]:
    sd = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(sd, dict):
        raise LPIPSUnavailable(f"{path} does not hold a state dict")
    return sd.get("state_dict", sd)


def load_lpips(weights: str | os.PathLike[str], backbone: str | os.PathLike[str] | None = None) -> LPIPSVGG:
    """Build LPIPS-VGG from local files (layouts in the module docstring); raises LPIPSUnavailable saying why."""
    weights = Path(weights)
    if not weights.is_file():
        raise LPIPSUnavailable(f"LPIPS weights file {weights} does not exist")
    sd = _load(weights)
    lins = {}
    for i in range(len(LAYER_CHANNELS)):
        key = next((k for k in (f"lin{i}.model.1.weight", f"lin{i}.weight") if k in sd), None)
        if key is None:
            raise LPIPSUnavailable(f"{weights} lacks the linear layer lin{i} of LPIPS (lin{i}.model.1.weight)")
        lins[f"{i}.weight"] = sd[key].reshape(1, LAYER_CHANNELS[i], 1, 1)
    trunk = _trunk_keys(sd, r"net\.slice\d\.")
    if not trunk:
        if backbone is None:
            raise LPIPSUnavailable(f"{weights} holds only LPIPS's linear layers; set {BACKBONE_ENV} to torchvision's "
                                   f"VGG-16 weights (vgg16-397923af.pth)")
        if not Path(backbone).is_file():
            raise LPIPSUnavailable(f"VGG-16 backbone file {backbone} does not exist")
        trunk = _trunk_keys(_load(Path(backbone)), r"features\.")
    model = LPIPSVGG()
    try:
        model.features.load_state_dict(trunk, strict=True)
        model.lins.load_state_dict(lins, strict=True)
    except RuntimeError as e:
        raise LPIPSUnavailable(f"LPIPS weights do not fit VGG-16: {str(e).splitlines()[0]}") from e
    return model.eval()


@dataclass
class LPIPSSetting:
    """Where LPIPS comes from in this run: a model, or None and the reason."""

    model: LPIPSVGG | None
    reason: str | None  # why model is None


def lpips_from_env() -> LPIPSSetting:
    """The LPIPS model configured through the environment (read now, not at import), or the reason there is none."""
    weights = os.environ.get(WEIGHTS_ENV, "").strip()
    if not weights:
        return LPIPSSetting(None, f"no local LPIPS weights configured (set {WEIGHTS_ENV}); LPIPS is not reported")
    try:
        return LPIPSSetting(load_lpips(weights, os.environ.get(BACKBONE_ENV, "").strip() or None), None)
    except LPIPSUnavailable as e:
        return LPIPSSetting(None, str(e))


def lpips_distance(model: LPIPSVGG, pred: Tensor, target: Tensor) -> float:
    """LPIPS of one image pair. [H, W, 3] in [0, 1] x2 -> float (0 = identical)."""
    with torch.no_grad():
        a = pred.permute(2, 0, 1)[None].float()
        b = target.permute(2, 0, 1)[None].float()
        return float(model(a, b)[0])


def mean_lpips(model: LPIPSVGG, pairs: list[tuple[Tensor, Tensor]]) -> float:
    """LPIPS averaged over views (the 3DGS convention)."""
    if not pairs:
        raise ValueError("mean_lpips needs at least one image pair")
    return sum(lpips_distance(model, p, t) for p, t in pairs) / len(pairs)


__all__ = ["LPIPSVGG", "LPIPSSetting", "LPIPSUnavailable", "load_lpips", "lpips_from_env", "lpips_distance",
           "mean_lpips", "WEIGHTS_ENV", "BACKBONE_ENV"]
