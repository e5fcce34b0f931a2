"""sRGB transfer functions (IEC 61966-2-1), numpy, for the ``space="linear"`` option of the restorer.

Private minimal stand-in: swap for ``pipeline.scene.colour`` (``srgb_to_linear`` / ``linear_to_srgb``) once that
module lands; the numba kernel ``_kernels.dewater`` inlines the same formulas.
"""

from __future__ import annotations

import numpy as np


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] → linear light, same shape (float64)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] → sRGB-encoded values, same shape (float64)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)
