"""The sRGB transfer functions (IEC 61966-2-1), exact piecewise form, for numpy arrays and torch tensors.

``srgb_to_linear`` is the EOTF (encoded value → linear light), ``linear_to_srgb`` its inverse (the encoding a
camera applies before writing 8-bit files). Both take values in [0, 1]; values below the linear segment's
threshold (negatives included) follow the linear segment, so neither produces NaN. The result has the input's
type (numpy in, numpy out; torch in, torch out; a Python float gives a numpy float64).

>>> round(float(srgb_to_linear(0.5)), 5)
0.21404
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

ArrayT = TypeVar("ArrayT")

SRGB_THRESHOLD = 0.04045  # encoded value where the linear segment ends
LINEAR_THRESHOLD = 0.0031308  # the same point in linear light
SLOPE = 12.92
GAMMA = 2.4
OFFSET = 0.055


def _is_torch(x: object) -> bool:
    return type(x).__module__.startswith("torch")


def srgb_to_linear(x: ArrayT) -> ArrayT:
    """sRGB-encoded [0, 1] → linear light [0, 1]: x/12.92 up to 0.04045, ((x + 0.055)/1.055)^2.4 above."""
    if _is_torch(x):
        import torch  # lazy: only torch inputs need torch; numpy callers stay torch-free

        power = ((x.clamp(min=SRGB_THRESHOLD) + OFFSET) / (1 + OFFSET)) ** GAMMA  # type: ignore[attr-defined]
        return torch.where(x <= SRGB_THRESHOLD, x / SLOPE, power)  # type: ignore[return-value,operator]
    a = np.asarray(x, dtype=np.float64) if not isinstance(x, np.ndarray) else x
    power = ((np.maximum(a, SRGB_THRESHOLD) + OFFSET) / (1 + OFFSET)) ** GAMMA
    return np.where(a <= SRGB_THRESHOLD, a / SLOPE, power)  # type: ignore[return-value]


def linear_to_srgb(x: ArrayT) -> ArrayT:
    """Linear light [0, 1] → sRGB-encoded [0, 1]: 12.92·x up to 0.0031308, 1.055·x^(1/2.4) − 0.055 above."""
    if _is_torch(x):
        import torch  # lazy: only torch inputs need torch; numpy callers stay torch-free

        power = (1 + OFFSET) * x.clamp(min=LINEAR_THRESHOLD) ** (1 / GAMMA) - OFFSET  # type: ignore[attr-defined]
        return torch.where(x <= LINEAR_THRESHOLD, x * SLOPE, power)  # type: ignore[return-value,operator]
    a = np.asarray(x, dtype=np.float64) if not isinstance(x, np.ndarray) else x
    power = (1 + OFFSET) * np.maximum(a, LINEAR_THRESHOLD) ** (1 / GAMMA) - OFFSET
    return np.where(a <= LINEAR_THRESHOLD, a * SLOPE, power)  # type: ignore[return-value]


__all__ = ["linear_to_srgb", "srgb_to_linear"]
