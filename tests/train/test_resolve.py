"""A job's TrainConfig is resolved in one place (pipeline.train.resolve), frozen, and everything else derives
from it: the mode probe's runs, the collapse guard's retry. The medium's start iteration has one rule."""

from __future__ import annotations

import json
from dataclasses import FrozenInstanceError, replace

import pytest

from pipeline.config import MediumConfig, SynthConfig, TrainConfig, from_dict, to_dict, train_preset
from pipeline.job.options import JobOptions
from pipeline.scene.loader import load_images, load_scene
from pipeline.synth.procedural import generate_scene
from pipeline.train.guard import safer_config
from pipeline.train.probe import ProbeConfig, probe_config
from pipeline.train.resolve import medium_with_water, resolve_train_config
from pipeline.train.trainer import Trainer
from pipeline.water.controller import controller_settings, medium_start_iteration
from pipeline.water.decision import WaterDecision


def _water(water_type: str = "turbid") -> dict:
    """A water decision as the train stage reads it back from the job's water.json."""
    probs = {k: 0.8 if k == water_type else 0.1 for k in ("clear", "medium", "turbid")}
    decision = WaterDecision(water_type, probs, 0.5, 1.0, 8, controller_settings(water_type))  # type: ignore[arg-type]
    return json.loads(json.dumps(decision.to_dict()))


def test_the_resolved_config_is_frozen_and_carries_the_water_decision():
    water = _water("clear")
    cfg = resolve_train_config(JobOptions(mode="dualphys", seed=7, max_width=400), 1000, water, None)
    with pytest.raises(FrozenInstanceError):
        cfg.iterations = 1  # type: ignore[misc]
    with pytest.raises(FrozenInstanceError):
        cfg.medium.alpha_w = 2.0  # type: ignore[misc]
    assert (cfg.mode, cfg.seed, cfg.downscale) == ("dualphys", 7, 3)
    m = cfg.medium
    assert (m.lr_attenuation, m.lr_scattering, m.alpha_w, m.beta_w, m.start_fraction) == (
        water["lr_attenuation"], water["lr_scattering"], water["alpha"], water["beta"],
        water["medium_start_fraction"])
    assert m.init_optical_depth == tuple(water["init_optical_depth"])
    assert from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg)))) == cfg  # what train/config.json holds
    # plain splatting has no medium to adapt; a medium without water adaptation (ablation rows) ignores it
    assert resolve_train_config(JobOptions(mode="3dgs"), 1000, water, None).medium == MediumConfig()
    off = MediumConfig(water_adaptation=False)
    assert medium_with_water(off, water) is off


def test_auto_resolves_to_the_probe_base_and_then_to_the_probes_choice():
    water, opts = _water("turbid"), JobOptions(mode="auto", seed=3)
    base = resolve_train_config(opts, 240, water, None)
    assert base.mode == "dualphys" and base.medium == medium_with_water(MediumConfig(), water)
    sel = {"chosen": "homogeneous", "budget": {"sh_degree": 1, "max_gaussians": 40_000}}
    final = resolve_train_config(opts, 240, water, sel)
    assert (final.mode, final.sh_degree, final.densify.max_gaussians) == ("homogeneous", 1, 40_000)
    assert replace(final, mode=base.mode, sh_degree=base.sh_degree, densify=base.densify) == base
    assert resolve_train_config(opts, 240, water, {**sel, "chosen": "3dgs"}).medium == MediumConfig()
    with pytest.raises(ValueError, match="unknown training preset"):
        resolve_train_config(JobOptions(preset="slowest"), 240, None, None)


def test_the_probe_and_the_retry_derive_from_the_resolved_config():
    base = resolve_train_config(JobOptions(mode="auto", seed=5), 640, _water("clear"), None)
    pc = ProbeConfig()
    probe = probe_config(base, pc, 640, "homogeneous")
    assert (probe.mode, probe.seed, probe.backend, probe.iterations) == ("homogeneous", 5, base.backend,
                                                                         pc.warmup + pc.iterations)
    assert (probe.downscale, probe.sh_degree, probe.densify.max_gaussians) == (5, pc.sh_degree, pc.max_gaussians)
    assert (probe.checkpoint_every, probe.log_every, probe.eval_every) == (0, 0, 0)
    assert probe.medium.start_fraction == pc.warmup / probe.iterations
    # the water decision reaches the probe through the base, not a second time
    assert replace(probe.medium, start_fraction=base.medium.start_fraction,
                   lr_reference_iterations=base.medium.lr_reference_iterations) == base.medium
    safe, _ = safer_config(base)
    assert safe.medium.start_fraction == 0.5 and safe.densify.reset_every == base.iterations + 1
    assert replace(safe, densify=base.densify, medium=base.medium) == base


@pytest.mark.parametrize("preset", ["fast", "balanced", "paper"])
def test_iterations_change_the_runs_length_not_the_preset(preset):
    """``--iterations`` used to replace the preset: ``--preset fast --iterations 3000`` trained with a 300k
    Gaussian cap where ``--preset fast`` has 100k (and paper's none became 300k). It keeps the preset's cap and
    scales its checkpoint cadence with the run."""
    p = train_preset(preset)
    opts = JobOptions(preset=preset, mode="dualphys")
    assert resolve_train_config(replace(opts, iterations=p.iterations), 240, None, None) == \
        resolve_train_config(opts, 240, None, None)
    short = resolve_train_config(replace(opts, iterations=1500), 240, None, None)
    assert short.densify.max_gaussians == p.densify.max_gaussians
    assert short.checkpoint_every == round(p.checkpoint_every * 1500 / p.iterations)
    # the schedule is the run's: the 30k recipe compressed to 1500 iterations (a medium mode refines 1.5x longer)
    assert (short.iterations, short.sh_degree_interval, short.densify.refine_stop) == (1500, 50, 1125)


def test_the_demo_keeps_the_fast_presets_cap():
    """``dualphys demo`` runs ``JobOptions(mode="dualphys", iterations=1500)`` with the default preset (fast)."""
    cfg = resolve_train_config(JobOptions(mode="dualphys", iterations=1500), 240, None, None)
    assert (cfg.densify.max_gaussians, cfg.checkpoint_every) == (100_000, 250)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    root = generate_scene(SynthConfig(views=3, width=32, height=24, preset="medium", seed=0, n_points=300,
                                      supersample=1), tmp_path_factory.mktemp("tiny"))
    scene = load_scene(root)
    return scene, load_images(scene)


@pytest.mark.parametrize(("iterations", "fraction"), [(1001, 0.5), (5, 0.5), (10, 0.25), (1500, 1 / 3)])
def test_the_medium_starts_where_the_controller_says(tiny_scene, iterations, fraction):
    """The medium term rounded total x fraction with Python's round (halves to even), the controller's
    ``medium_start_iteration`` halves up: where the product is an even number and a half (the collapse guard's
    retry of a 1001-iteration run starts the medium at 0.5) they were one iteration apart. Now there is one
    rule. (1500 x 1/3 is the demo: no half, never in question.)"""
    scene, images = tiny_scene
    cfg = TrainConfig(mode="homogeneous", iterations=iterations, backend="cpu", log_every=0,
                      medium=MediumConfig(start_fraction=fraction))
    start = medium_start_iteration(iterations, fraction)
    assert Trainer(scene, images, cfg).medium.start == start
    settings = replace(controller_settings("medium"), medium_start_fraction=fraction)
    assert settings.medium_start(iterations) == start
    if iterations * fraction % 1 == 0.5:  # where the two rules disagreed
        assert int(round(iterations * fraction)) == start - 1
