"""Labelled training images from the synthetic generator: render scenes once, re-apply many waters.

Rendering (ray casting) is the expensive part, so each (scene seed, altitude) is rendered once with no water
(clean J and depth); every sample then draws a water of its class (:func:`.sampling.sample_water`), applies
the revised formation model with the pixel's ray length, and passes the result through the camera nuisances.
Splits are by scene seed, so held-out images show terrain, rocks and corals the classifier never saw.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.config import SynthConfig
from pipeline.scene.records import ray_length_factor
from pipeline.synth.procedural import make_camera, synth_views
from pipeline.synth.water import underwater_image
from pipeline.water.controller import WATER_TYPES
from pipeline.water.features import image_features
from pipeline.water.sampling import NuisanceSpec, camera_nuisance, sample_water, seabed_variation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RenderSpec:
    """How the clean scenes are rendered (small: the classifier reads pooled statistics only)."""

    width: int = 64
    height: int = 48
    views: int = 4  # per scene: survey path, two thirds looking down, one third looking forward
    altitudes_per_scene: int = 2  # one per log-spaced stratum of altitude_range, seeded by the scene seed
    altitude_range: tuple[float, float] = (1.0, 6.0)  # metres above the mean seabed
    optical_depth_range: tuple[float, float] = (0.2, 3.0)  # green β_D × median range; see visible_range_scale


@dataclass
class CleanView:
    J: np.ndarray  # [H, W, 3] clean radiance in [0, 1]
    r: np.ndarray  # [H, W] distance along the ray, metres


def render_clean(scene_seeds: Sequence[int], spec: RenderSpec) -> list[CleanView]:
    """Clean J and ray length of every view of every (seed, altitude)."""
    out = []
    for s in scene_seeds:
        alts = stratified_altitudes(spec.altitude_range, spec.altitudes_per_scene, np.random.default_rng([s, 17]))
        for alt in alts:
            cfg = SynthConfig(views=spec.views, width=spec.width, height=spec.height, preset="none", seed=int(s),
                              altitude=float(alt), supersample=1, noise_std=0.0)
            ray = ray_length_factor(make_camera(cfg))
            _, views = synth_views(cfg)
            out.extend(CleanView(sv.J, sv.depth * ray) for sv in views)
    log.debug("rendered %d clean views from %d scene seeds", len(out), len(scene_seeds))
    return out


def stratified_altitudes(lo_hi: tuple[float, float], k: int, rng: np.random.Generator) -> np.ndarray:
    """k altitudes, one log-uniform draw in each of k equal log-width strata of [lo, hi] (so a scene seed never
    gets only near-seabed views, where the water barely shows). [k]"""
    edges = np.linspace(np.log(lo_hi[0]), np.log(lo_hi[1]), k + 1)
    return np.exp(rng.uniform(edges[:-1], edges[1:]))


def visible_range_scale(beta_g: float, r: np.ndarray, tau_range: tuple[float, float]) -> float:
    """Factor on the ray lengths so the green optical depth at the median range, τ = β_G · median(r), lies in
    ``tau_range`` (1 when it already does).

    A single image fixes only β·r, never β alone, and an image with τ ≪ 1 shows almost no water at all, so it
    has no water type to learn. Clamping τ moves the camera away (or closer) just enough that the water shows;
    inside the range the rendered geometry is used as is.
    """
    tau = beta_g * float(np.median(r[np.isfinite(r)]))
    lo, hi = tau_range
    return lo / tau if tau < lo else hi / tau if tau > hi else 1.0


def make_samples(views: Sequence[CleanView], draws_per_class: int, rng: np.random.Generator,
                 tau_range: tuple[float, float] = (0.2, 3.0), nuisance: NuisanceSpec | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Features [N, F] and labels [N] (index into WATER_TYPES); N = len(views) · 3 · draws_per_class."""
    images, labels = [], []
    for v in views:
        for label, water_type in enumerate(WATER_TYPES):
            for _ in range(draws_per_class):
                J = seabed_variation(v.J, rng)
                water = sample_water(water_type, rng)
                r = v.r * visible_range_scale(water.beta_D[1], v.r, tau_range)
                img = camera_nuisance(underwater_image(J, r, water), rng, nuisance)
                images.append(img)
                labels.append(label)
    x = torch.from_numpy(np.stack(images).astype(np.float32)).permute(0, 3, 1, 2)  # [N, 3, H, W]
    feats = torch.cat([image_features(chunk) for chunk in x.split(256)])
    return feats, torch.tensor(labels, dtype=torch.long)
