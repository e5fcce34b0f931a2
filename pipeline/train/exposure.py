"""Each training view's exposure and white balance, learned beside the Gaussians and the water.

The loss compares the model's (neutral-exposure) image with the view's photo brought to neutral exposure
(:func:`pipeline.scene.exposure.neutral` of its log gains [3], linear light), so neither the Gaussians' colours nor
the water absorb a frame's exposure. The gains have their own Adam; each step updates only the view rendered, then
the set is made mean-neutral again (a projection, so a step's gradient stays on its view). A small penalty on the
log gains keeps a view whose content no other view shares at neutral exposure. They start where the water fit put
them (:mod:`pipeline.medium.exposure_fit`) in medium modes; with ``TrainConfig.exposure`` "fit" (the medium modes'
default) they stay there: learned beside the medium, they absorbed its misfit (docs/DECISIONS.md,
"Exposure per view"). In ``3dgs`` they start from the sparse points' gains without water
(:func:`exposure_without_water`). After training every photo's gains are measured again against the model
(:mod:`pipeline.train.photo_exposure`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.medium.estimate import gather_observations
from pipeline.medium.exposure_fit import fit_exposure_only
from pipeline.medium.fall_off import FallOff, as_photographed, log_fall_off_map
from pipeline.scene.exposure import neutral
from pipeline.scene.records import Scene, View

log = logging.getLogger(__name__)

EXPOSURE_LR_FINAL = 0.1  # the gains' learning rate decays exponentially to this share of TrainConfig.exposure_lr


class ViewExposure:
    """Log gains [V, 3] of the training views, their optimiser and their penalty."""

    def __init__(self, n_views: int, space: str, lr: float, weight: float, iterations: int,
                 init: Sequence[Sequence[float]] | None = None, device: torch.device | str = "cpu", *,
                 source: str = "learned in training", evidence: float | None = None,
                 fall_off: FallOff | None = None):
        self.space, self.lr, self.weight, self.iterations = space, lr, weight, max(1, iterations)
        self.source, self.evidence = source, evidence
        self.fall_off = fall_off  # the survey's in-frame fall-off, divided out of every photo with its gains
        self._field: dict[tuple[int, int], Tensor] = {}  # its log field [H, W, 1] per image size
        start = np.zeros((n_views, 3)) if init is None else np.asarray(init, dtype=np.float64).reshape(n_views, 3)
        self.log_gain = nn.ParameterList(
            [nn.Parameter(torch.tensor(row, dtype=torch.float32, device=device)) for row in start])
        self.learned = lr > 0  # lr 0: the gains are held where they start (TrainConfig.exposure "fit")
        for p in self.log_gain:
            p.requires_grad_(self.learned)
        self.optimizer = torch.optim.Adam(list(self.log_gain), lr=lr, eps=1e-15)

    def correct(self, i: int, target: Tensor) -> Tensor:
        """View ``i``'s photo [H, W, 3] (physics space) at neutral exposure and even light (the survey's
        fall-off divided out when it is measured), differentiable in its gains."""
        return neutral(target, self.log_gain[i] + self.log_field(*target.shape[:2], target.device), self.space)

    def log_field(self, height: int, width: int, device: torch.device | str = "cpu") -> Tensor:
        """The survey's log fall-off [H, W, 1] over an image of that size (a zero scalar when none is removed)."""
        if self.fall_off is None or self.fall_off.log_field is None:
            return torch.zeros((), device=device)
        key = (height, width)
        if key not in self._field:
            self._field[key] = torch.as_tensor(log_fall_off_map(width, height, self.fall_off.log_field)[..., None],
                                               dtype=torch.float32, device=device)
        return self._field[key]

    def photographed(self, x: np.ndarray) -> np.ndarray:
        """A prediction [H, W, 3] (physics space, even light) as the camera recorded it: the survey's fall-off
        put back where training divided it out (:func:`pipeline.medium.fall_off.log_fall_off_map`), unclipped;
        ``x`` itself when none was."""
        return as_photographed(x, None, None if self.fall_off is None else self.fall_off.log_field, self.space)

    def penalty(self, i: int) -> Tensor:
        """The weighted penalty on view ``i``'s log gains (the step's loss term "exposure"; 0 when held)."""
        return self.weight * (self.log_gain[i] ** 2).sum() if self.learned else self.log_gain[i].new_zeros(())

    def step(self, iteration: int) -> None:
        """Adam on the views that have a gradient, then the set made mean-neutral again (nothing when held)."""
        if not self.learned:
            return
        for g in self.optimizer.param_groups:
            g["lr"] = self.lr * EXPOSURE_LR_FINAL ** (iteration / self.iterations)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            mean = torch.stack(list(self.log_gain)).mean(0)
            for p in self.log_gain:
                p.sub_(mean)

    def gains(self) -> np.ndarray:
        """The views' gains [V, 3] (linear light, geometric mean 1 per channel)."""
        with torch.no_grad():
            return torch.stack(list(self.log_gain)).exp().cpu().numpy().astype(np.float64)

    def record(self, names: Sequence[str]) -> dict[str, Any]:
        """:func:`exposure_record` of these views' gains, with where they came from."""
        return {**exposure_record(names, self.gains()), "source": self.source,
                "evidence": None if self.evidence is None else round(float(self.evidence), 2),
                "fall_off": None if self.fall_off is None else self.fall_off.record}

    def state_dict(self) -> dict[str, Any]:
        return {"log_gain": torch.stack([p.detach().clone() for p in self.log_gain]),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        with torch.no_grad():
            for p, row in zip(self.log_gain, sd["log_gain"], strict=True):
                p.copy_(row)
        self.optimizer.load_state_dict(sd["optimizer"])


def exposure_record(names: Sequence[str], gains: np.ndarray) -> dict[str, Any]:
    """What train_result.json and the report keep of the learned exposure: each view's gains and the spread."""
    g = np.asarray(gains, dtype=np.float64).reshape(-1, 3)
    dev = np.abs(np.log(g)) if len(g) else np.zeros((0, 3))
    return {"views": {n: [round(float(x), 4) for x in row] for n, row in zip(names, g, strict=True)},
            "space": "linear light, geometric mean 1 per channel over the training views",
            "max_deviation": round(float(np.expm1(dev.max())) if dev.size else 0.0, 4)}


def exposure_without_water(scene: Scene, views: Sequence[View], images: Sequence[Any], space: str
                           ) -> tuple[list | None, float | None]:
    """Plain splatting's start: the views' log gains [V, 3] measured from the sparse points with no water between
    (:func:`~pipeline.medium.exposure_fit.fit_exposure_only`; zero on a fixed camera) and their evidence; (None,
    None) without sightings. Started at 1, the Gaussians' view-dependent colour took up most of a video's exposure
    change (RUIE A188: ±5 % learned of ±42 %)."""
    if not len(scene.points):
        return None, None
    obs = gather_observations(scene.points, views, images, scene.sightings)
    if obs.point.size == 0:
        return None, None
    lg, evidence = fit_exposure_only(obs, len(views), space)
    log.info("exposure from the sparse points without water (evidence %.1f): gains up to %.1f %% from the mean",
             evidence, 100 * float(np.expm1(np.abs(lg).max())) if lg.size else 0.0)
    return lg.tolist(), evidence


__all__ = ["ViewExposure", "exposure_record", "exposure_without_water"]
