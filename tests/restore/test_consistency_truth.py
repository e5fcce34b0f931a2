"""The truth-free colour-consistency score ranks restorations made from a generated scene's truth: the true
water best, ahead of no restoration and of the water's β off by 2x either way, in every water type."""

from __future__ import annotations

import pytest

from pipeline.config import SynthConfig
from pipeline.restore.consistency_truth import scene_consistency
from pipeline.synth.procedural import generate_scene


@pytest.mark.parametrize("preset", ["clear", "medium", "turbid"])
def test_true_water_scores_best(preset, tmp_path):
    root = generate_scene(SynthConfig(views=6, width=64, height=48, preset=preset, seed=2), tmp_path / preset)
    res = scene_consistency(root, beta_scales=(1.0, 0.5, 2.0))
    assert res["photo"]["defined"] and res["x1"]["defined"], res["x1"]["reason"]
    assert res["photo"]["n_points"] > 1000
    true = res["x1"]["share"]
    assert true < 0.2
    for wrong in ("x0.5", "x2"):  # worse by far, or refused: a channel saturated or flattened by the wrong water
        r = res[wrong]
        assert (r["defined"] and true < 0.5 * r["share"]) or (not r["defined"] and "lost their contrast" in r["reason"])
