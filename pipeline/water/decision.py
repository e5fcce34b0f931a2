"""Classify a scene's water from a few of its images and turn the class into controller settings."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.water.classifier import WaterClassifier, load_classifier
from pipeline.water.controller import (
    WATER_TYPES,
    ControllerConfig,
    ControllerSettings,
    WaterType,
    controller_settings,
    water_index,
)
from pipeline.water.features import blue_green_ratio, image_features, resize_short_side

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WaterDecision:
    """The classifier's verdict on a scene and the settings the controller derives from it."""

    water_type: WaterType  # argmax of the averaged probabilities
    probabilities: dict[str, float]  # eq. 14 softmax, averaged over the images: {"clear": p, "medium": p, ...}
    index_w: float  # standardised blue/green indicator in [0, 1] (controller.water_index); 1 = blue
    bg_ratio: float  # the mean blue/green ratio the index was computed from
    n_images: int  # how many images were averaged
    settings: ControllerSettings  # learning rates, α, β, medium start

    @property
    def lr_attenuation(self) -> float:
        return self.settings.lr_attenuation

    @property
    def lr_scattering(self) -> float:
        return self.settings.lr_scattering

    @property
    def alpha(self) -> float:
        return self.settings.alpha

    @property
    def beta(self) -> float:
        return self.settings.beta

    @property
    def medium_start_fraction(self) -> float:
        return self.settings.medium_start_fraction

    def to_dict(self) -> dict:
        """Flat JSON-able record for the report."""
        s = self.settings.to_dict()
        s.pop("water_type")
        return {"water_type": self.water_type, "probabilities": dict(self.probabilities), "index_w": self.index_w,
                "bg_ratio": self.bg_ratio, "n_images": self.n_images, **s}


def images_to_tensor(image: np.ndarray) -> torch.Tensor:
    """One image [H, W, 3] (float in [0, 1], or uint8 / uint16) → [1, 3, H, W] float32."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got shape {a.shape}")
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / 255.0
    elif a.dtype == np.uint16:
        a = a.astype(np.float32) / 65535.0
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    if not torch.isfinite(t).all():
        raise ValueError("image holds NaN or infinite values")
    return t.permute(2, 0, 1)[None].clamp(0.0, 1.0)


def classify(images: Sequence[np.ndarray], *, classifier: WaterClassifier | None = None,
             controller: ControllerConfig | None = None) -> WaterDecision:
    """Water type of a scene from a few of its images ([H, W, 3] each; sizes may differ).

    Probabilities are averaged over the images (a scene has one water type; averaging damps a frame that
    looks into open water or at a close rock). The index w uses the geometric mean over the images of each
    image's blue/green ratio of mean colours. ``classifier`` defaults to the shipped weights (loaded on first use).
    """
    if len(images) == 0:
        raise ValueError("classify needs at least one image")
    model = classifier if classifier is not None else load_classifier()
    feats, ratios = [], []
    for img in images:
        x = resize_short_side(images_to_tensor(img))  # [1, 3, h, w]
        feats.append(image_features(x, resize=False))
        ratios.append(blue_green_ratio(x))
    with torch.no_grad():
        probs = model.probabilities(torch.cat(feats)).mean(dim=0)  # [3]
    bg = float(torch.cat(ratios).double().log().mean().exp())  # geometric mean over images
    water_type = WATER_TYPES[int(probs.argmax())]
    decision = WaterDecision(
        water_type=water_type,
        probabilities={k: float(p) for k, p in zip(WATER_TYPES, probs)},
        index_w=water_index(bg),
        bg_ratio=bg,
        n_images=len(images),
        settings=controller_settings(water_type, controller),
    )
    log.info("water type %s (p = %s, w = %.2f) from %d images", water_type,
             ", ".join(f"{k} {v:.2f}" for k, v in decision.probabilities.items()), decision.index_w, len(images))
    return decision
