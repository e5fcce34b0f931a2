"""Issue 39, item 2 at test size: per-frame exposure and white balance. The same generated medium-water scene twice,
once as photographed by a fixed camera and once with every frame's exposure within ±30 % and white balance within
±10 % (pipeline.synth.exposure); a whole homogeneous job on each. The job measures each frame's gains, reports them,
and restores the photos at the survey's mean exposure, as well as it restores the fixed camera's."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.export.report import build_report
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.synth.exposure import EXPOSURE_FILE, expose_scene
from pipeline.synth.photo import PhotoSynthConfig, default_textures_dir, generate_photo_scene

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not default_textures_dir().is_dir(),
                                                   reason="shared/data/textures is not beside the repository")]


@pytest.fixture(scope="module")
def jobs(tmp_path_factory):
    root = tmp_path_factory.mktemp("exposure")
    plain = generate_photo_scene(PhotoSynthConfig(views=16, width=400, height=300, preset="medium", seed=0),
                                 root / "plain")
    varied = root / "varied"
    shutil.copytree(plain, varied)
    expose_scene(varied, 0.3, 0.1, seed=0)
    out = {}
    for name, scene in (("plain", plain), ("varied", varied)):
        run_job(root / f"job-{name}", JobOptions(source=str(scene / "images"), mode="homogeneous", iterations=400,
                                                 max_width=100, colour_space="srgb"))
        out[name] = (scene, JobLayout(root / f"job-{name}"))
    return out


def test_gains_are_recovered(jobs, record_property):
    scene, layout = jobs["varied"]
    truth = json.loads((scene / EXPOSURE_FILE).read_text())["gains"]
    exposure = json.loads(layout.train_result.read_text())["exposure"]
    trained, got = exposure["views"], exposure["photos"]  # training views; every photo, measured against the model
    names = sorted(got)
    assert len(names) == 16 and set(trained) < set(got)
    lt, lg = (np.log([g[n] for n in names]) for g in (truth, got))
    on = [i for i, n in enumerate(names) if n in trained]  # the model's exposure: the training views' mean
    err = np.abs(np.expm1((lg - lg[on].mean(0)) - (lt - lt[on].mean(0))))
    record_property("gain_error", {"max": float(err.max()), "median": float(np.median(err))})
    assert err.max() < 0.05 and np.median(err) < 0.02, err
    # the fixed camera's survey: gains of 1 (the points showed no change), for every photo
    plain = json.loads(jobs["plain"][1].train_result.read_text())["exposure"]
    assert plain["max_deviation"] < 0.05, plain
    assert all(g == [1.0, 1.0, 1.0] for g in plain["photos"].values()), plain["photos"]


def test_restored_as_well_as_the_fixed_camera(jobs, record_property):
    scores = {k: json.loads(layout.restore_result.read_text())["truth"] for k, (_, layout) in jobs.items()}
    record_property("restored_psnr", {k: {p: t[p]["restored_psnr"] for p in ("train", "test")}
                                      for k, t in scores.items()})
    for pool in ("train", "test"):  # the held-out photos' gains are measured against the model
        assert scores["varied"][pool]["restored_psnr"] >= scores["plain"][pool]["restored_psnr"] - 0.5, scores
        assert scores["varied"][pool]["restored_psnr"] >= scores["varied"][pool]["photo_psnr"] + 4.0, scores


def test_the_report_lists_the_gains(jobs):
    _, layout = jobs["varied"]
    report = build_report(layout.root)
    assert report["exposure"]["max_deviation"] > 0.15
    assert set(report["exposure"]["views"]) == set(json.loads(layout.train_result.read_text())["exposure"]["views"])
