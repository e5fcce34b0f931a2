"""The coarse start (``TrainConfig.coarse_fraction``, issue 16): the first part of a run trains on the views and
targets shrunk ``coarse_downscale`` times, never past the medium's start (its PSNR floor: test_train)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from pipeline.config import TrainConfig, train_preset
from pipeline.ops.image_losses import photometric_losses
from pipeline.train.schedule import coarse_iterations
from pipeline.train.setup import shrink_image
from pipeline.train.trainer import Trainer
from tests.train.test_train import short_config


def test_the_rule_stops_at_the_medium_start():
    assert coarse_iterations(3000, 1 / 3, None) == 1000
    assert coarse_iterations(3000, 0.5, 1000) == 1000  # never past the medium's start
    assert coarse_iterations(3000, 0.2, 1000) == 600
    assert coarse_iterations(3000, 0.0, None) == 0
    assert train_preset("fast").coarse_fraction == pytest.approx(1 / 3)
    assert train_preset("paper").coarse_fraction == 0.0  # graphdeco's recipe unchanged
    with pytest.raises(ValueError, match="coarse_fraction"):
        TrainConfig(coarse_fraction=1.5)


def test_coarse_steps_render_and_score_the_shrunk_view(small_medium_scene):
    scene, images = small_medium_scene
    cfg = short_config(30, coarse_fraction=1 / 3, random_init_points=500)
    tr = Trainer(scene, images, cfg)
    assert tr.coarse_until == 10 and tr.coarse(10) and not tr.coarse(11)
    out = tr.render(0, 0, "RGB", coarse=True)
    assert tuple(out.image.shape) == (36, 48, 3)  # 96x72 halved
    assert out.info["width"] == 48 and out.info["height"] == 36  # densification normalises by this size
    # the loss a coarse step takes is L1 + SSIM against the area-averaged target (at neutral exposure: plain
    # splatting starts from the points' gains), at that size
    losses = tr.compute_losses(out, 0)
    target = tr.exposure.correct(0, tr.targets[0]) if tr.exposure is not None else tr.targets[0]
    want = photometric_losses(out.image, shrink_image(target, 36, 48), cfg.ssim_weight)
    for k in want:
        torch.testing.assert_close(losses[k], want[k], rtol=1e-6, atol=0)
    for _ in range(10):
        tr.step()
    assert tr.iteration == 10
    tr.step()  # iteration 11: the full size again
    full = tr.render(0, 0, "RGB", coarse=tr.coarse(tr.iteration + 1))
    assert tuple(full.image.shape) == (72, 96, 3)


def test_medium_modes_end_the_coarse_start_at_the_medium(small_medium_scene):
    scene, images = small_medium_scene
    cfg = dataclasses.replace(short_config(60, mode="homogeneous", random_init_points=500), coarse_fraction=0.9)
    tr = Trainer(scene, images, cfg)
    assert tr.medium is not None and tr.coarse_until == tr.medium.start == 20
