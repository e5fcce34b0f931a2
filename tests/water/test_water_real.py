"""The shipped classifier on real labelled photos (U45: blue ≈ clear, green ≈ medium, haze ≈ turbid).

The classifier never saw these images (it is trained on synthetic scenes only). Measured with the shipped
weights, rows = U45 folder, columns = predicted (clear, medium, turbid), one image at a time:

    blue   [ 9  5  1]
    green  [ 5  6  4]
    haze   [ 0  1 14]      29 / 45 = 64 % (chance 33 %)

Averaging all 15 images of a folder (how ``classify`` is used on a scene) gives the right class for all three.
The floors below are those numbers minus a margin of a few images, so a retrain that keeps the behaviour
passes and one that falls towards chance does not. Real photos differ from our renders in ways the training
distribution only partly covers: camera white balance and colour processing, strongly saturated green water
with red in its veil (which our classes put in turbid), JPEG, open-water backgrounds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.images import read_image
from pipeline.water import WATER_TYPES, classify

REPO = Path(__file__).resolve().parents[2]
U45 = REPO.parent / "shared" / "data" / "real" / "u45"
FOLDERS = {"blue": "clear", "green": "medium", "haze": "turbid"}

pytestmark = pytest.mark.skipif(not U45.is_dir(), reason=f"real check set not found at {U45}")


@pytest.fixture(scope="module")
def images() -> dict[str, list[np.ndarray]]:
    out = {f: [read_image(p) for p in sorted((U45 / f).glob("*.png"))] for f in FOLDERS}
    assert all(len(v) == 15 for v in out.values()), {k: len(v) for k, v in out.items()}
    return out


def test_u45_confusion_matrix(images):
    cm = np.zeros((3, 3), dtype=int)
    for i, folder in enumerate(FOLDERS):
        for img in images[folder]:
            cm[i, WATER_TYPES.index(classify([img]).closest)] += 1  # the class, also where one photo is "unknown"
    recall = np.diag(cm) / cm.sum(axis=1)
    assert np.trace(cm) / cm.sum() >= 0.55, cm  # measured 0.64; chance 0.33
    assert (recall >= 1 / 3).all(), cm  # measured ≥ 0.40 for every class
    assert recall[2] >= 0.8, cm  # haze → turbid, measured 14 / 15


def test_u45_scene_level_decision(images):
    for folder, expected in FOLDERS.items():
        d = classify(images[folder])
        assert d.water_type == expected, (folder, d.to_dict())
    assert classify(images["blue"]).index_w > classify(images["green"]).index_w  # bluer water → higher w
