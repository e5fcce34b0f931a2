"""A healthy model of real footage is never called collapsed (issue 39): plain splatting of the 19 RUIE A188 frames
(green coastal water, urchins on sand; shared/data/real), posed by the reference model there, trained briefly at
half size with an opacity reset half-way: no collapse, no retry and no warning.

The old rule (a view with under 90 % of its sparse points at alpha >= 0.5 "lost its scene") failed healthy
plain-splatting jobs whose dark surfaces are drawn faint over the black background (45-50 % point coverage on a
2,000-iteration model of a generated scene without water); short runs like this one do not reach that state
(99.6 % here), so the verdict's indifference to point coverage is tested at the unit level
(tests/train/test_quality.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.config import DensifyConfig, TrainConfig
from pipeline.scene.loader import load_scene
from pipeline.train.guard import train_checked
from pipeline.train.setup import load_training_images

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ruie-A188-A206"

pytestmark = pytest.mark.slow


def _cfg(iterations: int, downscale: int) -> TrainConfig:
    densify = DensifyConfig(refine_start=50, refine_stop=iterations - 100, refine_every=50,
                            reset_every=iterations // 2, max_gaussians=40_000)
    return TrainConfig(mode="3dgs", iterations=iterations, downscale=downscale, densify=densify, backend="cpu",
                       log_every=0, checkpoint_every=0, sh_degree_interval=200)


@pytest.mark.skipif(not REAL.is_dir(), reason="shared/data/real is not beside the repository")
def test_a_healthy_plain_model_of_real_footage_is_not_collapsed(tmp_path):
    scene = load_scene(REAL, workdir=tmp_path / "undistorted")  # sparse_ref: SIMPLE_RADIAL, undistorted here
    images = load_training_images(scene.views, 2, "srgb")  # half size, as the views are trained
    _, quality, recovery = train_checked(scene, images, _cfg(400, 2), tmp_path / "train", min_iterations=0)
    assert not quality["collapsed"] and recovery is None and quality["warnings"] == [], quality["warnings"]
    assert quality["coverage_min"] > 0.5, quality["coverage_min"]
