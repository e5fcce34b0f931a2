"""A photo's exposure and white balance as a gain per channel on linear light, and its removal.

Video and camera stills change exposure and white balance from frame to frame (auto exposure, lamps, a towed
camera's gain). A camera applies both to the sensor's linear signal before its tone curve, so view v's photo is
``encode(g_v · L)`` where L is the linear light a fixed camera would record and g_v [3] the view's gains. The
gains are only known relative to one another: a survey's set is mean-neutral (the mean of log g over views is 0
per channel), the exposure of a camera that never changed.

``neutral`` undoes a view's gains in the space the physics runs in: on linear light it divides; on sRGB-encoded
values it decodes, divides and encodes again (the exact inverse of the camera's order). It works on numpy arrays
and torch tensors (differentiable in the gains).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

from pipeline.scene.colour import linear_to_srgb, srgb_to_linear

ArrayT = TypeVar("ArrayT")


def neutral(x: ArrayT, log_gain, space: str = "srgb") -> ArrayT:
    """``x`` [..., 3] (values in ``space``: "srgb" encoded or "linear") as the photo of gains exp(``log_gain``)
    [3] would have been at neutral exposure."""
    if space not in ("srgb", "linear"):
        raise ValueError(f"unknown colour space {space!r}")
    if type(x).__module__.startswith("torch"):
        import torch  # lazy: only torch inputs need torch; numpy callers stay torch-free

        inv = torch.exp(-torch.as_tensor(log_gain, dtype=x.dtype, device=x.device))  # type: ignore[attr-defined]
    else:
        inv = np.exp(-np.asarray(log_gain, dtype=np.float64))
    if space == "linear":
        return x * inv  # type: ignore[operator,return-value]
    return linear_to_srgb(srgb_to_linear(x) * inv)  # type: ignore[operator,return-value]


def exposed(x: ArrayT, log_gain, space: str = "srgb") -> ArrayT:
    """The inverse of :func:`neutral`: ``x`` at neutral exposure as a camera with gains exp(``log_gain``) records
    it (no clipping: the caller clips where a sensor would)."""
    return neutral(x, -np.asarray(log_gain, dtype=np.float64), space)


def mean_neutral(log_gains: np.ndarray) -> np.ndarray:
    """[V, 3] log gains shifted so their mean over views is 0 per channel."""
    lg = np.asarray(log_gains, dtype=np.float64)
    return lg - lg.mean(axis=0, keepdims=True) if len(lg) else lg


__all__ = ["exposed", "mean_neutral", "neutral"]
