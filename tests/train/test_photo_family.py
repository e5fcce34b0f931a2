"""Issue 11's bar at test size, on scenes we did not make the way our model assumes: the photo-textured family
(real seabed photographs, a ray-marched heightfield, water applied per supersample, signal-dependent noise;
``pipeline.synth.photo``), through the whole job (SfM, mode auto, the fast schedule compressed to 1500
iterations). The water must not eat the scene, and the restoration must beat the photo on every held-out view.

Measured when written (16 views 200x150, seed 0): turbid chose homogeneous, 17.4k of 20.8k Gaussians, every
training view's sparse points covered, restored J 4.1 / 2.6 dB above the photo on the two held-out views (23.7
against 20.3 dB pooled); medium: homogeneous, 15.5k of 16.1k, +6.0 / +2.9 dB (24.5 against 20.0). Before the
fixes of issue 11 the turbid job ended with 2.1k Gaussians and restored J within 0.5 dB of the photo. About
5 min each on a loaded 2-core machine.
"""

from __future__ import annotations

import json

import pytest

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.synth.photo import PhotoSynthConfig, default_textures_dir, generate_photo_scene

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not default_textures_dir().is_dir(),
                                 reason="shared/data/textures/euvp-gtr-a is not beside the repository")]

# per water: (least gain over the photo on every held-out view, least pooled gain), dB; measured gains above
FLOORS = {"turbid": (1.0, 1.5), "medium": (2.0, 2.5)}
# per water: the confidence map's correlation with the restored error over the training photos must be below
# this (low confidence where the error is high). Measured 2026-11-27: turbid −0.26, medium −0.16; with the
# photo's-share confidence it replaced, −0.10 and −0.09 (the held-out pair: −0.01 / +0.10, before +0.01 / −0.13).
CONFIDENCE_CORRELATION = {"turbid": -0.15, "medium": -0.05}


@pytest.mark.parametrize("preset", ["turbid", "medium"])
def test_photo_textured_water_keeps_its_scene_and_is_restored(tmp_path, preset, record_property):
    scene = generate_photo_scene(PhotoSynthConfig(views=16, width=200, height=150, preset=preset, seed=0),
                                 tmp_path / "scene")
    # the generator's default water acts on sRGB values: the physics in the same space
    run_job(tmp_path / "job", JobOptions(source=str(scene / "images"), iterations=1500, colour_space="srgb"))
    r = json.loads(JobLayout(tmp_path / "job").report_json.read_text())
    q, rest = r["quality"], r["restoration"]
    gains = [p["restored_psnr"] - p["input_psnr"] for p in rest["per_view"]]
    record_property("result", {"mode": r["mode"], "n": q["n_gaussians"], "budget": q["budget"],
                               "point_coverage_min": q["point_coverage_min"], "gains": [round(g, 2) for g in gains],
                               "restored": round(rest["restored"]["psnr"], 2),
                               "photo": round(rest["input"]["psnr"], 2)})
    assert r["mode"] in ("homogeneous", "dualphys"), r["selection"]["reason"]  # there is water to model out
    assert not q["collapsed"], q["warnings"]
    # The SfM retry ladder now registers the three oblique frames the first pass left out (16 of 16 in medium
    # water); their far field is drawn partly beyond 3x the points' distance, a warning (issue 39's note).
    assert all("beyond 3x" in w for w in q["warnings"]), q["warnings"]
    assert q["point_coverage_min"] >= 0.98  # no training view lost its seabed
    assert q["n_gaussians"] >= 0.2 * q["budget"], (q["n_gaussians"], q["budget"])
    truth = json.loads(JobLayout(tmp_path / "job").restore_result.read_text())["truth"]
    record_property("confidence_error_correlation", {k: truth[k]["confidence_error_correlation"]
                                                     for k in ("train", "test")})
    per_view, pooled = FLOORS[preset]
    assert min(gains) >= per_view, gains
    assert rest["restored"]["psnr"] >= rest["input"]["psnr"] + pooled
    assert truth["train"]["confidence_error_correlation"] < CONFIDENCE_CORRELATION[preset], truth["train"]
