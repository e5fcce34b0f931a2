"""Ground-truth water for the synthetic scenes: presets and the revised underwater image-formation model.

The generator applies the revised model of Akkaynak & Treibitz (CVPR 2018, "A Revised Underwater Image
Formation Model"), per colour channel c, with separate coefficients for the direct signal and backscatter:

    I_c = J_c · exp(−β_D,c · r) + B∞_c · (1 − exp(−β_B,c · r))

where r is the distance along the pixel's ray (metres). This is the paper's eq. 3 with T_D = exp(−β_D r) and
T_B = exp(−β_B r); our medium model (``pipeline.medium``) must be able to express it exactly.

Preset values are representative band-averaged (R, G, B camera channel) coefficients in 1/m, chosen inside the
ranges of the Jerlov water types as tabulated by Solonenko & Mobley (Applied Optics 54(17), 2015, "Inherent
optical properties of Jerlov water types") and of the effective coefficients reported by Akkaynak et al.
(CVPR 2017, "What is the space of attenuation coefficients in underwater computer vision?"):

- ``clear``  ~ Jerlov I–IA open ocean: red is absorbed fastest, blue travels furthest, blue veil.
- ``medium`` ~ Jerlov II–III oceanic: stronger attenuation, still red > green > blue, blue-green veil.
- ``turbid`` ~ Jerlov 5C–7C coastal: strong scattering, green travels furthest, bright green-grey veil.

They are not measurements of one site; they are plausible, documented ground truth for tests.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# A generated scene's true water (preset, coefficients, units, the generator's config), in the scene folder.
# A scene path, not a job path: a job's water is what its classifier decided (JobLayout.classify).
TRUE_WATER_FILE = "water.json"


@dataclass(frozen=True)
class WaterParams:
    """Per-channel (R, G, B) water parameters of the revised model."""

    beta_D: tuple[float, float, float]  # 1/m, attenuation of the direct signal
    beta_B: tuple[float, float, float]  # 1/m, backscatter coefficient
    B_inf: tuple[float, float, float]  # veiling light (backscatter at infinite range), in [0, 1]

    def to_json(self) -> dict:
        d = asdict(self)
        d["units"] = {"beta_D": "1/m", "beta_B": "1/m", "B_inf": "linear image intensity [0, 1]"}
        return d


WATER_PRESETS: dict[str, WaterParams] = {
    "none": WaterParams(beta_D=(0.0, 0.0, 0.0), beta_B=(0.0, 0.0, 0.0), B_inf=(0.0, 0.0, 0.0)),
    "clear": WaterParams(beta_D=(0.40, 0.075, 0.045), beta_B=(0.30, 0.060, 0.040), B_inf=(0.03, 0.22, 0.42)),
    "medium": WaterParams(beta_D=(0.55, 0.17, 0.11), beta_B=(0.42, 0.14, 0.10), B_inf=(0.06, 0.30, 0.40)),
    "turbid": WaterParams(beta_D=(0.85, 0.48, 0.62), beta_B=(0.70, 0.45, 0.52), B_inf=(0.16, 0.38, 0.32)),
}


def underwater_image(J: np.ndarray, r: np.ndarray, water: WaterParams) -> np.ndarray:
    """Revised formation model (paper eq. 3 with separate β_D, β_B).

    Args:
        J: clean radiance, [H, W, 3] in [0, 1].
        r: distance along each pixel's ray in metres, [H, W] (may be +inf for rays that hit nothing).
        water: the coefficients.

    Returns:
        I: [H, W, 3], the underwater image (not clipped, not quantised).

    >>> I = underwater_image(np.ones((1, 1, 3)), np.zeros((1, 1)), WATER_PRESETS["medium"])
    >>> bool(np.allclose(I, 1.0))
    True
    """
    if J.ndim != 3 or J.shape[-1] != 3 or r.shape != J.shape[:2]:
        raise ValueError(f"expected J [H, W, 3] and r [H, W], got {J.shape} and {r.shape}")
    rr = r[..., None]
    bd, bb, binf = (np.asarray(v, dtype=np.float64) for v in (water.beta_D, water.beta_B, water.B_inf))
    with np.errstate(invalid="ignore"):  # inf·0 for the "none" preset at infinite range
        td = np.nan_to_num(np.exp(-bd * rr), nan=1.0)
        tb = np.nan_to_num(np.exp(-bb * rr), nan=1.0)
    return J * td + binf * (1.0 - tb)
