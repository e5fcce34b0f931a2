"""Each photo's exposure and white balance, removed before it is de-watered (:mod:`pipeline.scene.exposure`).

Training learned the gains of the views it trained on (train_result.json's ``exposure``). The photos it held out
were never fitted; their gains are measured here from the sparse points, against what the training views' colours
and the measured water predict for them (:func:`pipeline.medium.exposure_fit.new_view_gains`), so every restored
photo of the survey is at the same exposure: the mean over all of them.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pipeline.job.layout import JobLayout
from pipeline.medium.estimate import MediumEstimate, gather_observations
from pipeline.medium.exposure_fit import new_view_gains
from pipeline.scene.loader import load_scene
from pipeline.scene.records import scaled_view
from pipeline.train.setup import load_training_images

log = logging.getLogger(__name__)


def photo_gains(job: Path, state: dict) -> dict[str, np.ndarray]:
    """Image name → log gains [3] (linear light) for every photo whose exposure is known: learned in training,
    or measured for the held-out ones. Empty when the job did not learn exposure."""
    layout = JobLayout(job)
    record = (json.loads(layout.train_result.read_text()).get("exposure") or {}) if layout.train_result.exists() else {}
    gains = {name: np.log(np.asarray(g, dtype=np.float64)) for name, g in (record.get("views") or {}).items()}
    estimate = (state.get("medium") or {}).get("estimate")
    if not gains or not estimate:
        return gains
    scene = load_scene(layout.scene)
    names = [v.name for v in scene.views]
    if all(n in gains for n in names) or not len(scene.points):
        return gains
    cfg = state["config"]
    down = int(cfg.get("downscale", 1))
    space = cfg.get("colour_space", "srgb")
    images = load_training_images(scene.views, down, space)
    views = [scaled_view(v, down) for v in scene.views]
    obs = gather_observations(scene.points, views, [images[i] for i in range(len(views))], scene.sightings)
    known = {i: gains[n] for i, n in enumerate(names) if n in gains}
    fields = MediumEstimate.__dataclass_fields__
    est = MediumEstimate(**{k: v for k, v in estimate.items() if k in fields})
    for i, lg in new_view_gains(obs, known, est, space).items():
        gains[names[i]] = lg
        log.info("exposure of held-out photo %s measured from its sparse points: gains %s", names[i],
                 np.round(np.exp(lg), 3))
    mean = np.mean(list(gains.values()), axis=0)  # the survey's mean exposure: over every photo, held out too
    return {n: g - mean for n, g in gains.items()}
