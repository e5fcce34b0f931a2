"""Schedules follow the survey (pipeline.train.schedule): the preset's iterations and Gaussian cap for 24 views and
fewer, more for larger surveys by the rule's numbers; --iterations wins; the report states the rule."""

from __future__ import annotations

import json
from dataclasses import replace

import jsonschema
import numpy as np

from pipeline.config import medium_densify, train_preset
from pipeline.export.report import SCHEMA_FILE
from pipeline.export.report_html import _schedule
from pipeline.job.options import JobOptions
from pipeline.scene.records import Camera, Scene, View
from pipeline.train.resolve import resolve_train_config
from pipeline.train.schedule import survey_cap, survey_iterations
from pipeline.train.stage import job_schedule


def test_the_rule_keeps_24_views_and_grows_as_the_square_root_of_the_views():
    assert survey_iterations(3000, 24) == 3000
    assert survey_iterations(3000, 8) == 3000  # fewer views than the reference: the preset as it is
    assert survey_iterations(3000, 96) == 6000  # 4x the views: 2x the iterations
    assert survey_iterations(3000, 150) == 7500  # (150 / 24) ** 0.5 = 2.5
    assert survey_iterations(3000, 300) == 10607  # 3.54x: 35 passes over the views instead of 125
    assert survey_iterations(3000, 10_000) == 18_000  # capped at 6x
    assert survey_cap(100_000, 24) == 100_000 and survey_cap(100_000, 300) == 1_250_000
    assert survey_cap(0, 300) == 0  # a preset without a cap (paper) stays without
    assert survey_cap(300_000, 600) == 3_000_000  # budget.MAX_GAUSSIANS


def test_resolved_configs_by_survey_size():
    opts = JobOptions(mode="dualphys")
    fast = train_preset("fast")
    base = resolve_train_config(opts, 320, None, None)
    assert resolve_train_config(opts, 320, None, None, views=24) == base  # nothing moves at the reference
    assert resolve_train_config(opts, 320, None, None, views=12) == base
    # a medium mode refines 1.5x longer (DensifyConfig.medium_refine_factor), resolved here, once
    assert base.iterations == 3000 and base.densify == medium_densify(fast.densify)
    assert base.densify.refine_stop == 2250 and base.densify.medium_refine_factor == 1.0
    plain = resolve_train_config(replace(opts, mode="3dgs"), 320, None, None)
    assert plain.densify == fast.densify and plain.densify.refine_stop == 1500
    big = resolve_train_config(opts, 640, None, None, views=150)
    assert big.iterations == 7500 and big.densify.max_gaussians == 625_000
    # refinement and resets follow the run's length; the refine window stays the preset's
    assert (big.densify.refine_start, big.densify.refine_stop) == (125, 5625)
    assert big.densify.refine_every == fast.densify.refine_every == 100
    assert big.densify.reset_every == 1000 and big.checkpoint_every == 1250  # 6 checkpoints a run, as fast
    huge = resolve_train_config(opts, 640, None, None, views=300)
    assert huge.iterations == 10607 and huge.densify.max_gaussians == 1_250_000
    # --iterations wins over the rule; the budget still follows the survey
    short = resolve_train_config(replace(opts, iterations=2000), 640, None, None, views=300)
    assert short.iterations == 2000 and short.densify.max_gaussians == 1_250_000
    assert short.densify.refine_stop == 1500
    paper = resolve_train_config(replace(opts, preset="paper"), 640, None, None, views=96)
    assert paper.iterations == 60_000 and paper.densify.max_gaussians == 0


def _scene(n: int, w: int = 640, h: int = 480) -> Scene:
    cam = Camera(w, h, 500.0, 500.0, w / 2, h / 2)
    return Scene([View(f"{k:04d}.png", cam, np.eye(3), np.array([0.1 * k, 0.0, 0.0])) for k in range(n)])


def test_the_report_block_states_the_rule_and_its_numbers():
    opts = JobOptions(mode="dualphys", max_width=320)
    cfg = resolve_train_config(opts, 640, None, None, views=150)  # downscale 2: trains at 320x240
    train_views = _scene(131)  # 150 views, every 8th held out
    block = job_schedule(cfg, 150, train_views, explicit=False)
    assert block == {"views": 150, "train_views": 131, "width": 320, "height": 240, "pixels": 131 * 320 * 240,
                     "rule": "iterations = preset x clamp((views / 24) ^ 0.5, 1, 6)", "factor": 2.5,
                     "iterations": 7500, "explicit_iterations": False, "passes": 57.25, "refine_every": 100,
                     "refine_start": 125, "refine_stop": 5625,  # medium mode: x1.5, as the trainer runs it
                     "reset_every": 1000, "max_gaussians": 625_000, "medium_start": 2500,
                     "coarse_until": 2500, "coarse_width": 160, "coarse_height": 120}  # fast: the first third
    schema = json.loads(SCHEMA_FILE.read_text())["properties"]["schedule"]
    jsonschema.validate(block, schema)
    jsonschema.validate(None, schema)  # jobs trained before the rule
    html = _schedule(block)
    assert "7500 iterations" in html and "57.2 passes" in html and "625000" in html
    assert "iteration 2500" in html and "Iterations 1-2500 trained at 160x120" in html
    three = job_schedule(resolve_train_config(replace(opts, mode="3dgs", iterations=7500), 640, None, None, views=150),
                         150, train_views, explicit=True)
    assert three["refine_stop"] == 3750 and three["medium_start"] is None and three["explicit_iterations"]
    assert "set by --iterations" in _schedule(three)
