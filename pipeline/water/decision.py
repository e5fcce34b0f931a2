"""Classify a scene's water from a few of its images and turn the class into controller settings.

When the images are outside what the classifier was trained on (:mod:`.ood`: lamp-lit, very dark, blank or
otherwise far from the generated daylight scenes) the decision is ``water_type = "unknown"``, with the best guess
in ``closest`` and a plain ``reason``; the controller then uses :data:`UNKNOWN_SETTINGS_FROM`'s settings
(medium: the paper's base rates and α = β = 1, i.e. no class-specific push) and, in mode auto, the probe still
decides whether a water model is used at all. The job runs on and warns.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

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
from pipeline.water.ood import OodConfig, assess, clipped_fraction, illumination_falloff, mean_luma

log = logging.getLogger(__name__)

UNKNOWN = "unknown"
# Unknown water trains with the medium class's settings: the paper's base learning rates, α = β = 1 and the
# middle starting optical depth, the neutral choice between pushing towards attenuation (clear) or scattering
# (turbid) when the class is not known. In mode auto the probe still chooses whether to model water at all.
UNKNOWN_SETTINGS_FROM: WaterType = "medium"


@dataclass(frozen=True)
class WaterDecision:
    """The classifier's verdict on a scene and the settings the controller derives from it."""

    water_type: WaterType | Literal["unknown"]  # argmax of the averaged probabilities, or "unknown" (see known)
    probabilities: dict[str, float]  # eq. 14 softmax, averaged over the images: {"clear": p, "medium": p, ...}
    index_w: float  # standardised blue/green indicator in [0, 1] (controller.water_index); 1 = blue
    bg_ratio: float  # the mean blue/green ratio the index was computed from
    n_images: int  # how many images were averaged
    settings: ControllerSettings  # learning rates, α, β, medium start
    closest: WaterType | None = None  # the argmax class, also when the water is unknown (None: water_type)
    known: bool = True  # False: the images are outside the classifier's training (water_type "unknown")
    confidence: float = 1.0  # max probability × trust (.ood): low when the images are at or past its edge
    reason: str | None = None  # plain words when unknown or less trusted
    ood: dict | None = None  # the job's out-of-distribution statistics, trust and thresholds (.ood)

    def __post_init__(self) -> None:
        if self.closest is None and self.water_type != UNKNOWN:
            object.__setattr__(self, "closest", self.water_type)

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
        settings_from = s.pop("water_type")
        return {"water_type": self.water_type, "probabilities": dict(self.probabilities), "closest": self.closest,
                "known": self.known, "confidence": self.confidence, "reason": self.reason, "ood": self.ood,
                "settings_from": settings_from, "index_w": self.index_w, "bg_ratio": self.bg_ratio,
                "n_images": self.n_images, **s}


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
             controller: ControllerConfig | None = None, ood: OodConfig | None = None) -> WaterDecision:
    """Water type of a scene from a few of its images ([H, W, 3] each; sizes may differ).

    Probabilities are averaged over the images (a scene has one water type; averaging damps a frame that
    looks into open water or at a close rock). The index w uses the geometric mean over the images of each
    image's blue/green ratio of mean colours. ``classifier`` defaults to the shipped weights (loaded on first use).
    The images' out-of-distribution statistics (:func:`.ood.assess`, thresholds ``ood``) decide whether the
    class is known; unknown water gets :data:`UNKNOWN_SETTINGS_FROM`'s controller settings and a warning.
    """
    if len(images) == 0:
        raise ValueError("classify needs at least one image")
    model = classifier if classifier is not None else load_classifier()
    cfg = ood or OodConfig()
    feats, ratios, falloff, lum, clipped = [], [], [], [], []
    for img in images:
        x = resize_short_side(images_to_tensor(img))  # [1, 3, h, w]
        feats.append(image_features(x, resize=False))
        ratios.append(blue_green_ratio(x))
        falloff.append(illumination_falloff(x))
        lum.append(mean_luma(x))
        clipped.append(clipped_fraction(x))
    f = torch.cat(feats)
    with torch.no_grad():
        probs = model.probabilities(f).mean(dim=0)  # [3]
        distance = model.distance(f)  # [N] or None
    verdict = assess(distance, torch.cat(falloff), torch.cat(lum), torch.cat(clipped), cfg)
    bg = float(torch.cat(ratios).double().log().mean().exp())  # geometric mean over images
    closest = WATER_TYPES[int(probs.argmax())]
    water_type = closest if verdict.known else UNKNOWN
    p_max = float(probs.max())
    decision = WaterDecision(
        water_type=water_type,
        probabilities={k: float(p) for k, p in zip(WATER_TYPES, probs)},
        index_w=water_index(bg),
        bg_ratio=bg,
        n_images=len(images),
        settings=controller_settings(closest if verdict.known else UNKNOWN_SETTINGS_FROM, controller),
        closest=closest,
        known=verdict.known,
        confidence=p_max * verdict.trust,
        reason=verdict.reason,
        ood={**verdict.to_dict(), "thresholds": cfg.to_dict()},
    )
    probs_txt = ", ".join(f"{k} {v:.2f}" for k, v in decision.probabilities.items())
    if verdict.known:
        log.info("water type %s (p = %s, confidence %.2f, w = %.2f) from %d images", water_type, probs_txt,
                 decision.confidence, decision.index_w, len(images))
    else:
        log.warning("water type unknown (closest: %s, p = %s), %s; training with the %s water settings", closest,
                    probs_txt, verdict.reason, UNKNOWN_SETTINGS_FROM)
    return decision
