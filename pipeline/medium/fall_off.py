"""Whether the survey's in-frame fall-off is divided out of its photos, in training and in the restored photos.

The sparse points' exposure fit measures one grey field over the frame beside each view's gains
(:mod:`pipeline.medium.exposure_gains`): the lens's vignetting, a lamp's cone. Left in a photo, it is de-watered
with the seabed: a point darker at the frame's edge is restored darker there, and the restoration amplifies it
where it divides by a small transmission, so the same seabed changes colour as it crosses the frame (the truth-free
score, :mod:`pipeline.evaluate.consistency`, sees it as drift with range: edges are farther). And the model learns
it: a Gaussian takes the mean light of the places in the frame it was seen at, its view-dependent colour the rest.
So the field is divided out of every photo with its exposure where training compares it with the model
(:class:`pipeline.train.exposure.ViewExposure`) and where it is restored; whatever compares the model with a photo
puts it back (:func:`as_photographed`). The restored photos are what an even light
would have shown.

The field is divided out at its shape, not its level: it is scaled to a mean of 1 over the frame (linear light),
so the photos keep their overall exposure (the fit's field is 1 at the frame's centre; a lamp's 4x cone would
otherwise brighten every restored photo by its mean).

A field spanning less than :data:`MIN_SPAN` over the frame is the fit's noise (generated surveys without a
fall-off measure 1.00-1.04x) and is left in: dividing it out would only add that noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.medium.exposure_gains import field_map, field_values
from pipeline.scene.exposure import exposed

MIN_SPAN = 1.1  # brightest over darkest over the frame: below it the measured field is left in the photos


@dataclass(frozen=True)
class FallOff:
    """The field's coefficients [5] to divide out (None: left in) and what restore.json records."""

    log_field: np.ndarray | None
    record: dict[str, Any]


def fall_off_to_remove(estimate: dict | None) -> FallOff:
    """The decision for a job whose sparse points' water fit is ``estimate`` (:class:`~pipeline.medium.estimate
    .MediumEstimate` as a dict); its record goes into train_result.json's ``exposure`` block and restore.json."""
    est = estimate or {}
    theta, span = est.get("exposure_field"), est.get("field_span")
    if theta is None or span is None:
        return FallOff(None, {"removed": False, "span": None,
                              "reason": "not measured (no sparse water fit with image positions)"})
    if span < MIN_SPAN:
        return FallOff(None, {"removed": False, "span": span,
                              "reason": f"spans {span:.2f}x over the frame, below {MIN_SPAN}x: the fit's noise"})
    return FallOff(np.asarray(theta, np.float64), {"removed": True, "span": span, "log_field": list(theta),
                                                   "reason": f"spans {span:.2f}x over the frame"})


def field_level(theta: np.ndarray, grid: int = 32) -> float:
    """The log of the field's mean over the frame (linear light), over the centres of ``grid`` x ``grid`` cells."""
    t = (np.arange(grid) + 0.5) / grid * 2 - 1
    return float(np.log(np.mean(np.exp(field_values(np.stack(np.meshgrid(t, t), -1).reshape(-1, 2), theta)))))


def log_fall_off_at(xy: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The log fall-off divided out of a photo [M] at image positions ``xy`` [M, 2] (half-widths / half-heights
    from the centre): the field of coefficients ``theta`` [5] at a mean of 1 over the frame."""
    return field_values(xy, theta)[:, 0] - field_level(theta)


def log_fall_off_map(width: int, height: int, theta: np.ndarray) -> np.ndarray:
    """:func:`log_fall_off_at` over an image of that size at its pixel centres [height, width]
    (:func:`pipeline.medium.exposure_gains.field_map`)."""
    return field_map(width, height, theta) - field_level(theta)


def as_photographed(x: np.ndarray, log_gain: np.ndarray | None, theta: np.ndarray | None,
                    space: str = "srgb") -> np.ndarray:
    """A prediction [H, W, 3] (values in ``space``, neutral exposure, even light) as the camera recorded it: at
    exposure ``log_gain`` [3] (None: neutral) and with the fall-off of coefficients ``theta`` [5] put back (None:
    none was divided out); unclipped, ``x`` itself when neither applies."""
    lg = None if log_gain is None else np.asarray(log_gain, np.float64)
    if theta is not None:
        H, W = x.shape[:2]
        lg = (0.0 if lg is None else lg) + log_fall_off_map(W, H, theta)[..., None]
    return x if lg is None else exposed(x, lg, space)


__all__ = ["MIN_SPAN", "FallOff", "as_photographed", "fall_off_to_remove", "field_level", "log_fall_off_at",
           "log_fall_off_map"]
