"""Underwater image formation (paper eqs. 3, 4 and 6) as pure tensor functions.

Layout: images NCHW — J, A, B, I are [N, 3, H, W]; depth D and alpha are [N, 1, H, W]. D is the distance along
each pixel's ray in scene units, consistent across views (never normalised per frame), so a β learned here is
a real coefficient (1/scene-unit; 1/m once a metric scale is known).

Exponents are clamped to [0, MAX_EXPONENT]: exp(−80) is already below float32's smallest normal, and the clamp
keeps every value and gradient finite for D in [0, 1e4] and β in [0, 50].
"""

from __future__ import annotations

import torch
from torch import Tensor

MAX_EXPONENT = 80.0


def transmission(beta: Tensor, D: Tensor) -> Tensor:
    """T = exp(−β·D), the fraction of light surviving a path of length D. beta [3] or broadcastable; D [N,1,H,W]."""
    return torch.exp(-(beta.reshape(1, -1, 1, 1) * D.clamp(min=0)).clamp(0, MAX_EXPONENT))


def homogeneous_backscatter(D: Tensor, beta_b: Tensor, B_inf: Tensor) -> Tensor:
    """Paper eq. 6: B = B∞ · (1 − exp(−β·d)) per channel. D [N,1,H,W], beta_b [3], B_inf [3] → [N,3,H,W].

    >>> B = homogeneous_backscatter(torch.full((1, 1, 1, 1), 1e4), torch.ones(3), torch.tensor([.1, .2, .3]))
    >>> [round(float(x), 6) for x in B.flatten()]
    [0.1, 0.2, 0.3]
    """
    x = (beta_b.reshape(1, -1, 1, 1) * D.clamp(min=0)).clamp(0, MAX_EXPONENT)
    return B_inf.reshape(1, -1, 1, 1) * -torch.expm1(-x)


def classical_formation(J: Tensor, D: Tensor, beta_D: Tensor, beta_B: Tensor, B_inf: Tensor) -> Tensor:
    """Paper eq. 3 (revised model, Akkaynak & Treibitz 2018): I = J·exp(−β_D·D) + B∞·(1 − exp(−β_B·D))."""
    return J * transmission(beta_D, D) + homogeneous_backscatter(D, beta_B, B_inf)


def dualphys_formation(J: Tensor, A: Tensor, B: Tensor) -> Tensor:
    """Paper eq. 4: I = J · A(D, I_RGB) + B(D), all [N, 3, H, W]."""
    return J * A + B


def composite_over_water(J: Tensor, A: Tensor, B: Tensor, alpha: Tensor, B_inf: Tensor) -> Tensor:
    """Eq. 4 (:func:`dualphys_formation`) for a splatted pixel that is only partly covered (alpha < 1): what
    :class:`~pipeline.medium.model.Medium` renders.

    J is the alpha-premultiplied rendered radiance and A, B are evaluated at the alpha-normalised depth; the
    covered fraction alpha sees eq. 4 with its backscatter alpha·B, the uncovered fraction (1 − alpha) looks
    through water to infinity and sees the veiling light B∞:
        I = J·A + alpha·B + (1 − alpha)·B∞.
    With alpha = 1 this is exactly eq. 4. Shapes: J, A, B [N,3,H,W]; alpha [N,1,H,W]; B_inf [3].
    """
    return dualphys_formation(J, A, alpha * B) + (1.0 - alpha) * B_inf.reshape(1, -1, 1, 1)
