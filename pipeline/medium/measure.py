"""The water (and each view's exposure) measured from a scene's sparse points, remembered: the mode probe and the
ablation train several models on the same views, and each fit costs seconds."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np
import torch

from pipeline.medium.estimate import MediumEstimate, Observations, fit_medium, gather_observations
from pipeline.medium.exposure_fit import fit_with_exposure
from pipeline.scene.records import Sightings, View

_CACHE: dict[str, MediumEstimate | None] = {}  # the last few fits, keyed by their sightings and settings
_CACHE_SIZE = 4


def measure_water(points: np.ndarray, views: Sequence[View], images: Sequence[np.ndarray | torch.Tensor],
                  sightings: dict[str, Sightings] | None, init_optical_depth: Sequence[float],
                  exposure_space: str | None = None) -> MediumEstimate | None:
    """:func:`~pipeline.medium.estimate.fit_medium` of :func:`~pipeline.medium.estimate.gather_observations`; with
    ``exposure_space`` ("srgb" or "linear": the images' space) each view's exposure is fitted beside the water
    (:func:`~pipeline.medium.exposure_fit.fit_with_exposure`, the estimate's ``log_gains`` in the order of
    ``views``)."""
    return measure_observed(gather_observations(points, views, images, sightings), len(views), init_optical_depth,
                            exposure_space)


def measure_observed(obs: Observations, n_views: int, init_optical_depth: Sequence[float],
                     exposure_space: str | None = None) -> MediumEstimate | None:
    """:func:`measure_water` of sightings already gathered (``n_views``: the views they index)."""
    h = hashlib.sha1(str(exposure_space).encode())
    for a in (obs.point, obs.range, obs.colour, obs.view, np.asarray(init_optical_depth, dtype=np.float64)):
        h.update(np.ascontiguousarray(a).tobytes())
    key = h.hexdigest()
    if key not in _CACHE:
        while len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        if exposure_space is None:
            _CACHE[key] = fit_medium(obs, init_optical_depth)
        else:
            _CACHE[key] = fit_with_exposure(obs, n_views, init_optical_depth, exposure_space)[0]
    return _CACHE[key]
