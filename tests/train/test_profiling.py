"""The step profiler (pipeline.profiling): nothing when off, named sections when on, and the same training."""

from __future__ import annotations

import time

import pytest
import torch

from pipeline import profiling


def test_section_is_a_shared_no_op_when_off_and_times_when_on():
    assert profiling.section("a") is profiling.section("b")  # off: one shared no-op, nothing recorded
    with profiling.collecting() as sec:
        for _ in range(3):
            with profiling.section("outer"):
                with profiling.section("inner"):
                    time.sleep(0.01)
    assert sec["outer#"] == 3 and sec["inner#"] == 3
    assert 0.03 <= sec["inner"] <= sec["outer"] < 1.0
    assert profiling.section("a") is profiling.section("b")  # off again after the block
    with profiling.section("after"):
        pass
    assert "after" not in sec


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from pipeline.config import SynthConfig
    from pipeline.scene.images import read_image
    from pipeline.scene.loader import load_scene
    from pipeline.synth.procedural import generate_scene

    root = generate_scene(SynthConfig(views=4, width=64, height=48, preset="medium"), tmp_path_factory.mktemp("s"))
    scene = load_scene(root)
    return scene, [read_image(root / "images" / v.name) for v in scene.views]


def test_profiled_steps_name_their_parts_and_train_the_same(tiny_scene):
    """Six steps of plain splatting with the profiler on and off give the same Gaussians bit for bit; on,
    every step's parts are timed once per step and the inner sections add up to no more than the step. (A medium
    mode's setup alone took minutes on the loaded 2 cores; bench/job.py exercises the medium's section.)"""
    from pipeline.config import DensifyConfig, TrainConfig
    from pipeline.train.trainer import Trainer

    scene, images = tiny_scene
    cfg = TrainConfig(iterations=6, backend="cpu", log_every=0, mode="3dgs",
                      densify=DensifyConfig(refine_start=2, refine_stop=6, refine_every=2, reset_every=10_000))
    plain = Trainer(scene, images, cfg)  # each seeds the global generator (densification draws from it)
    plain.run()
    profiled = Trainer(scene, images, cfg)
    with profiling.collecting() as sec:
        profiled.run()
    for k in plain.gaussians:
        assert torch.equal(plain.gaussians[k], profiled.gaussians[k]), k
    for name in ("step", "render", "losses", "backward", "optimizer", "raster: project fwd",
                 "raster: composite fwd", "raster: composite bwd", "raster: project bwd"):
        assert sec[name + "#"] == 6, name
    assert sec["densify#"] == 12  # before and after backward
    assert sec["losses: photometric fwd#"] == 6
    inner = sum(sec[k] for k in ("render", "losses", "backward", "optimizer", "densify"))
    assert inner <= sec["step"]
    assert sec["raster: composite bwd"] + sec["raster: project bwd"] <= sec["backward"]


def test_warmup_calls_every_rasterizer_kernel():
    from pipeline.splat.warmup import compile_kernels

    first, second = compile_kernels(), compile_kernels()
    assert set(first) == {"sh None RGB", "sh 3 RGB+ED"}
    assert all(v < 5.0 for v in second.values())  # compiled or loaded once per process: a second call is a render
