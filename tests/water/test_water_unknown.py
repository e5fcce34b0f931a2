"""Water the classifier has not seen (issue 39.4): lamp-lit dark water, black and saturated frames come out
"unknown" with the medium water's settings; real daylight survey frames stay known.

Numbers from bench/water_ood.py (docs/DECISIONS.md "Water type: unknown water"): lamp-lit jobs have a median
falloff of 1.08-4.2 against the threshold 1.0; real daylight sets at most 0.16.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.records import ray_length_factor
from pipeline.synth.lamp import LampSpec, lamp_lit_image, lamp_lit_photo
from pipeline.synth.procedural import make_camera, synth_views
from pipeline.train.resolve import medium_with_water
from pipeline.water import WATER_TYPES, classify, controller_settings, load_classifier
from pipeline.water.classifier import classifier_from_dict, read_weights_record, save_classifier
from pipeline.water.decision import UNKNOWN_SETTINGS_FROM
from pipeline.water.ood import OodConfig, assess, clipped_fraction, illumination_falloff, mean_luma

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
REAL_SETS = ("ruie-A188-A206/images", "ruie-B571-B597/images", "aims-erub-mt81/images", "aims-ugar-mt3a/images",
             "u45/blue", "u45/green", "u45/haze")


def _small(img: np.ndarray, short: int = 96) -> np.ndarray:
    """Area-downscale a photo to a short side of ``short`` pixels (test size; the classifier reads 48)."""
    t = torch.from_numpy(img).permute(2, 0, 1)[None]
    s = short / min(img.shape[:2])
    size = (max(1, round(img.shape[0] * s)), max(1, round(img.shape[1] * s)))
    return torch.nn.functional.interpolate(t, size=size, mode="area")[0].permute(1, 2, 0).numpy()


def _assert_unknown(d) -> None:
    rec = d.to_dict()
    json.dumps(rec, allow_nan=False)  # no NaN or inf anywhere in what classify.json will hold
    assert d.water_type == "unknown" and not d.known and d.closest in WATER_TYPES
    assert d.confidence == 0.0 and d.reason and "outside the classifier's training" in d.reason
    assert rec["settings_from"] == UNKNOWN_SETTINGS_FROM == "medium"
    medium = controller_settings("medium")
    assert (d.lr_attenuation, d.lr_scattering, d.alpha, d.beta) == (medium.lr_attenuation, medium.lr_scattering,
                                                                     medium.alpha, medium.beta)
    assert all(math.isfinite(v) for v in d.probabilities.values())


def test_lamp_lit_generated_scene_is_unknown():
    """A generated seabed with its depth, lit by a lamp in dark green-brown water: unknown, the lamp named."""
    cfg = SynthConfig(views=3, width=64, height=48, preset="none", seed=3001, altitude=1.5, supersample=1,
                      noise_std=0.0)
    ray = ray_length_factor(make_camera(cfg))
    rng = np.random.default_rng(0)
    images = [lamp_lit_image(sv.J, sv.depth * ray, 1.0 / ray, rng) for sv in synth_views(cfg)[1]]
    d = classify(images)
    _assert_unknown(d)
    assert d.ood["falloff"] > OodConfig().falloff_max and "lamps" in d.reason, d.to_dict()


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real data not found at {REAL}")
def test_lamp_lit_real_frames_are_unknown_while_the_frames_themselves_are_known():
    """The reported failure, rebuilt: RUIE frames re-lit by a lamp at 1 m through a 90° lens look 'clear' to
    the classifier, which must not be trusted; the same frames in daylight are known."""
    paths = sorted((REAL / "ruie-A188-A206/images").iterdir())[::5][:3]
    frames = [_small(read_image(p)) for p in paths]
    rng = np.random.default_rng(1)
    lit = [lamp_lit_photo(f, 1.0, 90.0, rng, lamp=LampSpec(ambient=0.05)) for f in frames]
    d = classify(lit)
    _assert_unknown(d)
    assert d.closest == "clear", d.to_dict()  # what the classifier alone would have said (bench: p 0.70)
    assert d.ood["falloff"] > 3.0
    daylight = classify(frames)
    assert daylight.known and daylight.water_type == daylight.closest and daylight.confidence > 0.3


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real data not found at {REAL}")
@pytest.mark.parametrize("folder", REAL_SETS)
def test_real_daylight_sets_are_known(folder):
    paths = sorted(p for p in (REAL / folder).iterdir() if p.is_file())
    frames = [_small(read_image(p)) for p in (paths[0], paths[len(paths) // 2])]
    d = classify(frames)
    rec = d.to_dict()
    assert d.known and d.water_type in WATER_TYPES and rec["settings_from"] == d.water_type, rec
    assert d.ood["falloff"] < 0.5 and d.ood["distance"] < OodConfig().distance_max, rec
    assert 0.0 < d.confidence <= max(d.probabilities.values()) + 1e-6


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_black_and_saturated_frames_are_unknown_without_nan(value):
    d = classify([np.full((48, 64, 3), value, np.float32)] * 2)
    _assert_unknown(d)
    assert d.ood["clipped"] == 1.0 and "black or saturated" in d.reason


def test_falloff_measures_a_lit_disc_not_a_gradient():
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 48), torch.linspace(-1, 1, 64), indexing="ij")
    rho2 = (xx * 0.8) ** 2 + (yy * 0.6) ** 2  # corner at radius 1
    def img(y):
        return y[None, None].expand(1, 3, -1, -1).clamp(0, 1)
    spot = img(0.8 * torch.exp(-1.5 * rho2))  # log luma −1.5ρ²: Hessian eigenvalues −3, falloff 3
    assert float(illumination_falloff(spot)[0]) == pytest.approx(3.0, abs=0.15)
    ramp = img(0.2 + 0.3 * (xx + 1) / 2 + 0.1 * (yy + 1) / 2)  # daylight over a sloping seabed: no spot
    assert abs(float(illumination_falloff(ramp)[0])) < 0.3
    vignette = img(0.5 * (1 - 0.3 * rho2))  # the training's strongest vignetting: 0.70, below the threshold
    v = float(illumination_falloff(vignette)[0])
    assert v == pytest.approx(0.70, abs=0.03) and v < OodConfig().falloff_max
    tiny = torch.full((1, 3, 2, 5), 0.5)  # fewer than 3×3 blocks: no fit, 0
    assert illumination_falloff(tiny).tolist() == [0.0]
    assert mean_luma(torch.full((1, 3, 2, 2), 0.25)).tolist() == pytest.approx([0.25])
    assert clipped_fraction(torch.tensor([0.0, 0.5, 1.0, 0.3]).reshape(1, 1, 2, 2).expand(1, 3, 2, 2)).tolist() \
        == [0.5]


def test_assess_uses_job_medians_and_ramps_trust():
    cfg = OodConfig()
    ok = torch.tensor([0.1, 0.1, 5.0])  # one lamp-lit frame among three does not make the water unknown
    v = assess(torch.tensor([3.0, 3.0, 30.0]), ok, torch.full((3,), 0.4), torch.zeros(3), cfg)
    assert v.known and v.trust == 1.0 and v.reason is None and v.statistics["falloff"] == pytest.approx(0.1)
    mid = (cfg.distance_typical + cfg.distance_max) / 2  # halfway to the threshold: trust 0.5, still known
    v = assess(torch.tensor([mid]), torch.zeros(1), torch.full((1,), 0.4), torch.zeros(1), cfg)
    assert v.known and v.trust == pytest.approx(0.5) and "edge" in v.reason
    v = assess(None, torch.zeros(1), torch.full((1,), 0.02), torch.zeros(1), cfg)  # no distribution recorded
    assert not v.known and v.trust == 0.0 and "very dark" in v.reason and v.statistics["distance"] is None


def test_shipped_weights_carry_the_training_distribution(tmp_path):
    """The distribution survives a save/load exactly, and a file without it still loads (distance None)."""
    rec = read_weights_record()
    model = load_classifier()
    assert model.distribution is not None and rec["feature_distribution"]["shrinkage"] == 0.1
    z = torch.randn(5, len(rec["feature_names"]))
    again = classifier_from_dict(json.loads(save_classifier(model, tmp_path / "w.json").read_text()))
    assert torch.equal(again.distribution.whitening, model.distribution.whitening)
    assert torch.equal(again.distance(z), model.distance(z))
    assert torch.equal(model.distance(model.feature_mean[None])[0:1] * 0, torch.zeros(1))
    old = classifier_from_dict({k: v for k, v in rec.items() if k != "feature_distribution"})
    assert old.distribution is None and old.distance(z) is None


def test_unknown_decision_trains_with_the_medium_settings():
    d = classify([np.zeros((24, 32, 3), np.float32)]).to_dict()
    from pipeline.config import MediumConfig

    m = medium_with_water(MediumConfig(), d)
    medium = controller_settings("medium")
    assert (m.lr_attenuation, m.alpha_w, m.beta_w, m.init_optical_depth) == (
        medium.lr_attenuation, medium.alpha, medium.beta, medium.init_optical_depth)


def test_report_shows_unknown_water_with_its_closest_class_and_reason():
    import jsonschema

    from pipeline.export.report_html import water_sentence

    d = classify([np.ones((24, 32, 3), np.float32)]).to_dict()
    schema = json.loads((Path(__file__).resolve().parents[2] / "pipeline/data/report.schema.json").read_text())
    jsonschema.validate(json.loads(json.dumps(d)), schema["properties"]["water"])
    s = html.unescape(water_sentence(d))
    p = d["probabilities"][d["closest"]]
    assert s.startswith("<b>unknown</b> (closest: ") and f"{d['closest']}, p {p:.3f}, but the images" in s
    assert "trained with the medium water's settings" in s
    known = {"water_type": "clear", "probabilities": {"clear": 0.9, "medium": 0.1, "turbid": 0.0}}
    assert water_sentence(known) == "<b>clear</b> (p = 0.90)"  # a record from before this change
