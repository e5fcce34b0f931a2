"""No collapse: trained on generated underwater scenes, the medium carries the water instead of J absorbing it.

The scenes use the generator's true (metric) cameras, so depths are in metres and the learned coefficients
are directly comparable with the truth. "Effect" is measured on the training views as the mean over pixels of
(1 − A) for attenuation and of B for backscatter, each at the true depth against the learned model at the
rendered depth.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.config import MediumConfig, SynthConfig, TrainConfig, train_preset
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import ray_length_factor
from pipeline.synth.procedural import generate_scene
from pipeline.synth.water import WATER_PRESETS
from pipeline.train.resolve import medium_with_water
from pipeline.train.trainer import Trainer
from pipeline.water import classify


def _config(iterations: int, images) -> tuple[TrainConfig, dict]:
    """A short DualPhys run configured the way a job is: the classifier's decision through the controller."""
    decision = classify(images[::2]).to_dict()
    cfg = TrainConfig(mode="dualphys", iterations=iterations, sh_degree_interval=max(1, iterations // 30),
                      densify=train_preset("fast").densify.scaled(iterations / 30_000), backend="cpu", log_every=0,
                      medium=medium_with_water(MediumConfig(), decision))
    return cfg, decision


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["medium", "turbid"])
def test_learned_medium_carries_the_water(tmp_path, preset, record_property):
    root = generate_scene(SynthConfig(views=16, width=128, height=96, preset=preset, seed=3), tmp_path)
    scene = load_scene(root)
    images = [read_image(root / "images" / v.name) for v in scene.views]
    cfg, decision = _config(900, images)
    record_property("water", decision["water_type"])
    tr = Trainer(scene, images, cfg)
    tr.run([])
    water = WATER_PRESETS[preset]
    bd, bb, binf = (np.asarray(x) for x in (water.beta_D, water.beta_B, water.B_inf))
    true_att, true_bs, learned_att, learned_bs = [], [], [], []
    for i, v in enumerate(tr.views):
        r = np.load(root / "depth" / f"{v.name.rsplit('.', 1)[0]}.npy") * ray_length_factor(v.camera)
        true_att.append((1 - np.exp(-bd * r[..., None])).mean())
        true_bs.append((binf * (1 - np.exp(-bb * r[..., None]))).mean())
        with torch.no_grad():
            out = tr.render(i, tr.max_sh_degree, "RGB+ED")
            med, _ = tr.medium.apply(i, out.image, out.alpha, out.depth)
        learned_att.append(float((1 - med.A).mean()))
        learned_bs.append(float(med.B.mean()))
    ratios = {"attenuation": np.mean(learned_att) / np.mean(true_att),
              "backscatter": np.mean(learned_bs) / np.mean(true_bs)}
    record_property("effect_ratios", {k: round(float(v), 3) for k, v in ratios.items()})
    record_property("coefficients", tr.medium.effective_coefficients())
    assert ratios["attenuation"] >= 0.5, ratios
    assert ratios["backscatter"] >= 0.5, ratios
    assert ratios["attenuation"] <= 2.0 and ratios["backscatter"] <= 2.0, ratios  # nor an invented medium
