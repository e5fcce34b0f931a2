"""The colour-consistency score (:mod:`pipeline.evaluate.consistency`) checked where the truth is known.

On a generated scene, restorations are formed straight from the generator's truth, no training: J = (I − B)/A
per pixel with the true depth, by the restorer's own per-pixel physics
(:func:`pipeline.restore.dewater.dewater_reference`, no model prior, no gain cap), once with the true
water and once with both β scaled (β off by 2x: halved and doubled). The score must rank the true water
best: better than the photos (no restoration) and better than either wrong water. Everything is in the true
PINHOLE geometry of ``sparse_gt`` (or ``pinhole/`` for a distorted scene), with the true tracks.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.evaluate.consistency import colour_consistency
from pipeline.medium.estimate import Observations, gather_observations
from pipeline.restore.dewater import dewater_reference
from pipeline.restore.records import MediumMaps
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import Scene, View, ray_length_factor
from pipeline.synth.ground_truth import FAR_DEPTH_M, PINHOLE_DIR
from pipeline.synth.water import TRUE_WATER_FILE

UNCAPPED = 1e6  # a gain cap no pixel reaches: the plain J = (I − B)/A


def truth_restoration(photo: np.ndarray, depth: np.ndarray, view: View, water: dict, beta_scale: float = 1.0,
                      max_gain: float = UNCAPPED) -> np.ndarray:
    """``photo`` [H, W, 3] restored with the scene's true water (``TRUE_WATER_FILE``), β_D and β_B times
    ``beta_scale``, at the true depth [H, W] (camera z, metres), each channel's gain at most ``max_gain``
    (default: none; the restorer's own cap, 8, under-corrects far red in turbid water), quantised to 8 bits like
    a restored file. [H, W, 3] float in [0, 1]"""
    r = depth * ray_length_factor(view.camera)
    surface = depth < FAR_DEPTH_M
    medium = MediumMaps(np.asarray(water["beta_D"], np.float64) * beta_scale,
                        np.asarray(water["beta_B"], np.float64) * beta_scale, np.asarray(water["B_inf"], np.float64))
    J, _, _ = dewater_reference(photo, np.where(surface, r, 0.0), surface, medium, max_gain=max_gain,
                                space=water.get("water_space", "srgb"))
    return np.round(J * 255.0) / 255.0


def scene_consistency(root: str | Path, beta_scales: Sequence[float] = (1.0, 0.5, 2.0),
                      max_gain: float = UNCAPPED) -> dict[str, dict]:
    """The score of the photos of generated scene ``root`` and of each truth restoration (keyed ``"x<scale>"``,
    e.g. ``"x1"``, ``"x0.5"``; gain cap ``max_gain``), every one against the photos; ``"photo"`` scores the
    photos against themselves (share 1)."""
    root = Path(root)
    water = json.loads((root / TRUE_WATER_FILE).read_text())
    geo = root / PINHOLE_DIR if (root / PINHOLE_DIR).is_dir() else root
    scene: Scene = load_scene(geo)
    photos = [read_image(geo / "images" / v.name) for v in scene.views]
    depths = [np.load(geo / "depth" / f"{Path(v.name).stem}.npy") for v in scene.views]
    base = gather_observations(scene.points, scene.views, photos, scene.sightings)
    out = {"photo": colour_consistency(base, base)}
    for s in beta_scales:
        restored = [truth_restoration(p, d, v, water, s, max_gain)
                    for p, d, v in zip(photos, depths, scene.views, strict=True)]
        obs = gather_observations(scene.points, scene.views, restored, scene.sightings)
        out[f"x{s:g}"] = colour_consistency(base, Observations(obs.point, obs.range, obs.colour))
    return out
