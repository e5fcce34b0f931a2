"""A scene lit by the vehicle's own lamps in dark water (the water classifier's unknown-water test cases).

Daylight from above lights a seabed evenly; a lamp on the vehicle lights a disc. With the lamp beside the camera,
a surface point at range r seen at angle θ off the lamp axis gets

    I = J · L · cosⁿθ / r² · exp(−2 β_D r)                       (light out to the point and back)
      + s · L · cosⁿθ · (1 − exp(−2 β_D r)) · B∞ / max(B∞)      (lamp light scattered back by the water)
      + a · underwater_image(J, r, water)                       (the little daylight left, a ≈ 0.1-0.2)

then a camera exposes it (gain to a target mean luma), adds noise, clips and quantises to 8 bits. A crude model
(no lamp offset from the camera, single scattering folded into s), enough to give the statistics of lamp-lit
footage: a bright, natural-coloured centre falling off to dark, water-tinted edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.synth.water import WaterParams, underwater_image

LUMA = np.array([0.299, 0.587, 0.114])
# Dark green-brown temperate coastal water: CDOM takes the blue, particles and water the red; green goes furthest.
GREEN_BROWN = WaterParams(beta_D=(0.55, 0.28, 0.9), beta_B=(0.4, 0.22, 0.6), B_inf=(0.16, 0.2, 0.07))


@dataclass(frozen=True)
class LampSpec:
    """The lamp and camera of :func:`lamp_lit_image`."""

    colour: tuple[float, float, float] = (1.0, 0.88, 0.7)  # warm white (halogen-like) relative RGB
    exponent: float = 4.0  # n of the cosⁿθ beam pattern
    ambient: float = 0.15  # a: the daylight left, as a fraction of a surface scene's
    backscatter: float = 0.1  # s: strength of the lamp light scattered back
    min_range: float = 0.3  # m: 1/r² is capped here (the lamp is not a point at the lens)
    target_luma: float = 0.25  # the camera's auto-exposure target (mean luma)
    noise_std: float = 0.004


def lamp_lit_image(J: np.ndarray, r: np.ndarray, cos_axis: np.ndarray, rng: np.random.Generator,
                   water: WaterParams = GREEN_BROWN, lamp: LampSpec | None = None) -> np.ndarray:
    """The lamp-lit photo (see the module docstring) of clean radiance J [H, W, 3] at ray lengths r [H, W]
    (metres), cos_axis [H, W] the cosine of each pixel's angle to the lamp axis → [H, W, 3] in [0, 1], 8-bit
    values."""
    if J.ndim != 3 or J.shape[-1] != 3 or r.shape != J.shape[:2] or cos_axis.shape != r.shape:
        raise ValueError(f"expected J [H, W, 3], r and cos_axis [H, W], got {J.shape}, {r.shape}, {cos_axis.shape}")
    sp = lamp or LampSpec()
    colour, bd = np.asarray(sp.colour), np.asarray(water.beta_D)
    veil = np.asarray(water.B_inf) / max(water.B_inf)
    rr = r[..., None]
    beam = (np.clip(cos_axis, 0.0, 1.0) ** sp.exponent)[..., None] * colour  # [H, W, 3]
    direct = J * beam / np.maximum(rr, sp.min_range) ** 2 * np.exp(-2.0 * bd * rr)
    back = sp.backscatter * beam * (1.0 - np.exp(-2.0 * bd * rr)) * veil
    x = direct + back + sp.ambient * underwater_image(J, r, water)
    x = x * sp.target_luma / max(float((x @ LUMA).mean()), 1e-6)
    x = np.clip(x + rng.normal(0.0, sp.noise_std, x.shape), 0.0, 1.0)
    return np.round(x * 255.0) / 255.0


def pinhole_rays(height: int, width: int, fov_deg: float) -> np.ndarray:
    """Ray length per unit camera depth (= 1 / cos of the angle to the optical axis) of a centred pinhole with
    horizontal field of view ``fov_deg``. [H, W]"""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    u = (np.arange(width) + 0.5 - width / 2) / f
    v = (np.arange(height) + 0.5 - height / 2) / f
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def lamp_lit_photo(photo: np.ndarray, distance: float, fov_deg: float, rng: np.random.Generator,
                   water: WaterParams = GREEN_BROWN, lamp: LampSpec | None = None) -> np.ndarray:
    """A daylight photo [H, W, 3] re-lit as if taken by lamp in dark water, the scene a plane at ``distance``
    metres square to the camera (no depth is known). → [H, W, 3]"""
    ray = pinhole_rays(photo.shape[0], photo.shape[1], fov_deg)
    return lamp_lit_image(np.asarray(photo, dtype=np.float64), distance * ray, 1.0 / ray, rng, water, lamp)
