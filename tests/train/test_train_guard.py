"""A job never ends ``done`` with a blank model: a collapse is recovered on a safer schedule or fails the train
stage with ``model_collapsed`` (pipeline.train.guard)."""

from __future__ import annotations

import json

import pytest
import torch

from pipeline.config import DensifyConfig, MediumConfig, SynthConfig, TrainConfig
from pipeline.job.layout import CHECKPOINT_NAME, COLLAPSED_NAME, RECOVERY_NAME
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.synth.procedural import generate_scene
from pipeline.train.guard import ModelCollapsedError, safer_config, train_checked

ITERATIONS = 120


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = generate_scene(SynthConfig(views=8, width=80, height=60, preset="turbid", seed=2),
                          tmp_path_factory.mktemp("g"))
    s = load_scene(root)
    return s, [read_image(root / "images" / v.name) for v in s.views]


def _cfg() -> TrainConfig:
    densify = DensifyConfig(refine_start=20, refine_stop=100, refine_every=15, reset_every=10_000,
                            max_gaussians=20_000)
    return TrainConfig(mode="homogeneous", iterations=ITERATIONS, sh_degree_interval=40, densify=densify,
                       backend="cpu", log_every=0, checkpoint_every=0, medium=MediumConfig(start_fraction=0.3))


def _blank_at(iteration: int, times: list[int]):
    """A hook that makes every Gaussian transparent at ``iteration`` (what the veil did to turbid scenes),
    in as many training attempts as ``times`` has entries."""

    def hook(tr, metrics):
        if tr.iteration == iteration and times:
            times.pop()
            with torch.no_grad():
                tr.gaussians["opacities"].fill_(-12.0)

    return hook


def test_a_healthy_run_has_no_recovery(scene, tmp_path):
    s, images = scene
    res, quality, recovery = train_checked(s, images, _cfg(), tmp_path, min_iterations=0)
    assert recovery is None and not quality["collapsed"] and quality["warnings"] == []
    assert quality["point_coverage_min"] >= 0.98 and quality["coverage_min"] > 0.9
    assert len(quality["per_view"]) == len(s.views) and quality["n_gaussians"] == res.gaussians["means"].shape[0]


def test_collapse_is_recovered_on_a_safer_schedule(scene, tmp_path):
    s, images = scene
    res, quality, recovery = train_checked(s, images, _cfg(), tmp_path, min_iterations=0,
                                           hooks=[_blank_at(ITERATIONS, [1])])
    assert recovery is not None and recovery["first_attempt"]["point_coverage_min"] == 0.0
    assert (tmp_path / COLLAPSED_NAME).is_file() and json.loads((tmp_path / RECOVERY_NAME).read_text()) == recovery
    assert not quality["collapsed"] and quality["point_coverage_min"] >= 0.98
    assert quality["warnings"][0].startswith("recovered: the first homogeneous attempt lost the scene")
    # A resumed stage goes straight to the safer attempt (its checkpoint is complete: nothing is retrained).
    res2, quality2, recovery2 = train_checked(s, images, _cfg(), tmp_path, min_iterations=0)
    assert recovery2 == recovery and res2.iteration == ITERATIONS
    torch.testing.assert_close(res2.gaussians["means"], res.gaussians["means"])


def test_a_model_that_stays_blank_fails_with_model_collapsed(scene, tmp_path):
    s, images = scene
    with pytest.raises(ModelCollapsedError, match="lost the scene") as e:
        train_checked(s, images, _cfg(), tmp_path, min_iterations=0,
                      hooks=[_blank_at(ITERATIONS - 10, [1, 1])])
    assert e.value.code == "model_collapsed"
    assert (tmp_path / COLLAPSED_NAME).is_file() and (tmp_path / CHECKPOINT_NAME).is_file()  # both attempts kept


def test_a_short_run_is_warned_about_not_retried(scene, tmp_path):
    s, images = scene
    _, quality, recovery = train_checked(s, images, _cfg(), tmp_path, hooks=[_blank_at(ITERATIONS, [1])])
    assert recovery is None and quality["collapsed"] and not (tmp_path / COLLAPSED_NAME).exists()
    assert "too short to judge" in quality["warnings"][-1]


def test_safer_config_changes_only_the_schedule_and_the_surface_term():
    cfg = _cfg()
    safe, changes = safer_config(cfg)
    assert safe.densify.reset_every > safe.iterations and safe.medium.start_fraction == 0.5
    assert safe.medium.loss_weights["w_surface"] == pytest.approx(0.25)
    assert (safe.mode, safe.iterations, safe.seed) == (cfg.mode, cfg.iterations, cfg.seed)
    assert cfg.densify.reset_every == 10_000  # the original is untouched
    assert set(changes) == {"opacity_reset", "medium_start_fraction", "w_surface"}
