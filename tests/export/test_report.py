"""A whole job on a tiny generated scene (ingest -> sfm -> classify -> train -> evaluate -> export): the
evaluation's numbers, report.json against its schema, and report.html as a standalone page in Chromium."""

from __future__ import annotations

import base64
import io
import json
import math
import re
import shutil
import subprocess

import jsonschema
import numpy as np
import pytest

from pipeline.config import SynthConfig
from pipeline.evaluate.evaluation import evaluate_job
from pipeline.export.report import SCHEMA_FILE, build_report, validate_report, write_report
from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.job.table import STAGES
from pipeline.restore.views import NOTHING_TO_RESTORE
from pipeline.synth.procedural import generate_scene

ITERATIONS = 150
pytestmark = pytest.mark.slow  # the module's job: SfM, training, restore (~90 s)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    scene = generate_scene(SynthConfig(views=12, width=96, height=72, preset="medium", seed=0), root / "scene")
    results = run_job(root / "job", JobOptions(source=str(scene / "images"), mode="dualphys", iterations=ITERATIONS,
                                               colour_space="srgb"))  # the generator's water acts on sRGB values
    return root / "job", results


def _report(job_dir):
    return json.loads(JobLayout(job_dir).report_json.read_text())


def test_stage_order_puts_evaluate_between_train_and_export():
    assert STAGES == ("ingest", "sfm", "classify", "train", "evaluate", "restore", "survey", "export")


def test_report_json_follows_its_schema_and_holds_real_numbers(job, record_property):
    job_dir, results = job
    r = _report(job_dir)
    validate_report(r)
    assert r["schema_version"] == 1 and r["mode"] == "dualphys" and r["preset"] == "fast"
    assert r["selection"] == {"mode": "dualphys", "requested": "dualphys", "reason": "requested by the user"}
    assert r["water"]["water_type"] in ("clear", "medium", "turbid")
    t = r["metrics"]["test"]
    assert t["n_views"] == 2 and t["views"] == ["frame_0000.png", "frame_0008.png"]  # every 8th by name
    assert 18.0 < t["psnr"] < 40.0 and 0.3 < t["ssim"] <= 1.0
    assert t["lpips"] is None and "DUALPHYS_LPIPS_WEIGHTS" in t["lpips_reason"]
    rest = r["restoration"]
    record_property("restored_psnr", rest["restored"]["psnr"])
    record_property("photo_psnr", rest["input"]["psnr"])
    record_property("test_psnr", t["psnr"])
    assert 5.0 < rest["restored"]["psnr"] < 40.0 and math.isfinite(rest["input"]["psnr"])
    # The model with water, rendered from the true cameras, must look like the photos about as well as it does
    # from its own cameras: the check that the true cameras were carried into the model's world correctly.
    assert abs(rest["with_water"]["psnr"] - t["psnr"]) < 3.0
    for pv in rest["per_view"]:  # the veil left on (or taken off twice) per channel: no larger than the error
        assert len(pv["bias"]) == 3 and np.mean(np.square(pv["bias"])) <= 10 ** (-pv["restored_psnr"] / 10) + 1e-9
    seen = rest["seen"]  # restoration over the pixels some training view saw
    record_property("restored_seen_psnr", seen["restored_psnr"])
    assert 0.3 < seen["fraction"] <= 1.0 and [p["name"] for p in seen["per_view"]] == rest["views"]
    assert 5.0 < seen["restored_psnr"] < 50.0 and math.isfinite(seen["input_psnr"])
    assert rest["alignment"]["rot_err_deg_mean"] < 2.0 and 0 < rest["metres_per_unit"]
    coef = rest["coefficients"]
    record_property("beta_D_rel_error", coef["beta_D"]["rel_error"])
    assert coef["beta_D"]["true"] == [0.55, 0.17, 0.11] and coef["units"]["beta_D"] == "1/m"
    assert all(0 < b < 5 for b in coef["beta_D"]["estimated"])
    assert rest["depth"]["scale_aligned"]["rel_error"] < 0.3 and rest["depth"]["at_alignment_scale"]["n_pixels"] > 0
    tm = r["timings"]
    assert set(tm["stages_s"]) == set(STAGES) and all(v is not None and v >= 0 for v in tm["stages_s"].values())
    assert tm["total_s"] == pytest.approx(sum(tm["stages_s"].values()))
    assert tm["train_iterations_per_s"] > 0 and tm["render_ms_per_view"]["median"] > 0
    assert r["model"]["n_gaussians"] == results["train"]["n_gaussians"] > 0
    assert r["outputs"] == {f: 12 for f in ("restored", "with_water", "attenuation", "backscatter", "depth")}
    c = r["consistency"]  # the truth-free score, on the restored files at the sparse model's sightings
    record_property("consistency_share", c["share"])
    assert c["defined"] and c["reason"] is None and c["n_views"] == 12 and c["n_points"] >= 30
    assert c["range_ratio"] > 1.1 and c["photo_score"] > 0 and c["share"] == pytest.approx(
        c["restored_score"] / c["photo_score"])
    assert "consistency" not in r["restore"]  # lifted to the top, not repeated


def test_speed_vs_error_is_increasing_in_time_and_ends_at_the_final_model(job):
    job_dir, _ = job
    sve = _report(job_dir)["speed_vs_error"]
    pts = sve["points"]
    assert 6 <= len(pts) <= 9
    assert all(b["elapsed_s"] > a["elapsed_s"] for a, b in zip(pts, pts[1:]))
    assert all(b["iteration"] > a["iteration"] for a, b in zip(pts, pts[1:]))
    assert pts[-1]["iteration"] == ITERATIONS and sve["includes_final"]
    assert pts[-1]["psnr"] > pts[0]["psnr"]  # training helped
    png = (JobLayout(job_dir).output / sve["plot"]).read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")


def test_schema_rejects_a_report_missing_required_fields(job):
    job_dir, _ = job
    schema = json.loads(SCHEMA_FILE.read_text())
    r = _report(job_dir)
    for broken in ({k: v for k, v in r.items() if k != "speed_vs_error"},
                   {**r, "metrics": {"test": {k: v for k, v in r["metrics"]["test"].items() if k != "lpips"}}},
                   {**r, "schema_version": 2}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(broken, schema)


def test_report_without_ground_truth_has_null_restoration(job, tmp_path):
    job_dir, _ = job
    copy = JobLayout(tmp_path / "job")
    shutil.copytree(job_dir, copy.root, ignore=shutil.ignore_patterns(copy.evaluate_renders.name, "report.*",
                                                                      copy.curve_png.name))
    atomic_write_json(copy.evaluate, evaluate_job(copy.root, None, stages=STAGES[:4]))
    paths = write_report(copy.root, copy.output)
    assert set(paths) == {copy.report_json, copy.report_html, copy.curve_png}
    r = json.loads(copy.report_json.read_text())
    validate_report(r)
    assert r["restoration"] is None and r["model"]["metres_per_unit"] is None
    assert "No ground truth" in copy.report_html.read_text()
    sel = {"requested": "auto", "chosen": "3dgs", "reason": "probe: no water found", "probe": {"3dgs": {"psnr": 30}}}
    copy.selection.write_text(json.dumps(sel))
    r = build_report(copy.root)
    validate_report(r)
    assert r["selection"] == {**sel, "mode": "3dgs"}
    # the classifier's decision, also from a job folder written before its file was renamed
    assert r["water"] == json.loads(copy.classify.read_text()) and r["water"]["water_type"]
    copy.classify.rename(copy.legacy_classify)
    assert build_report(copy.root)["water"] == r["water"]


def _png_shape(data: bytes) -> tuple[int, ...]:
    import matplotlib.image as mpimg

    return mpimg.imread(io.BytesIO(data), format="png").shape


def test_report_html_stands_alone_with_every_image_embedded(job):
    job_dir, _ = job
    html = JobLayout(job_dir).report_html.read_text()
    srcs = re.findall(r'<img[^>]*\ssrc="([^"]*)"', html)
    # 4 restored photos x (photo, restored, confidence, 2 crops) + 2 held-out views x (photo, model, restored,
    # truth) + 2 x (A, B, depth) + the curve + the survey's two mosaics and hillshade
    assert len(srcs) == 4 * 5 + 2 * 4 + 2 * 3 + 1 + 3
    for src in srcs:
        assert src.startswith("data:image/png;base64,"), src[:40]
        shape = _png_shape(base64.b64decode(src.split(",", 1)[1], validate=True))
        assert len(shape) == 3 and shape[0] >= 60 and shape[1] >= 80
    assert not re.search(r'(src|href)="(?!data:)', html)  # nothing the page would fetch
    assert "restored J vs true clean J" in html and "Water type" in html and "Config" in html
    photos = html[html.index("<h2>Your photos, de-watered</h2>"):html.index("<h2>Held-out views</h2>")]
    assert "12 photos restored at their own resolution (96x72)" in photos and "held-out photos" in photos


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium is not installed (.ci/run installs it)")
def test_report_html_renders_in_headless_chromium(job, tmp_path):
    import matplotlib.image as mpimg

    job_dir, _ = job
    shot = tmp_path / "shot.png"
    subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
                    "--window-size=1200,2000", JobLayout(job_dir).report_html.resolve().as_uri()],
                   check=True, capture_output=True, timeout=120)
    px = mpimg.imread(shot)[..., :3]
    assert px.shape[:2] == (2000, 1200)
    # A blank or broken page is flat; the report's text, tables and pictures are not.
    assert float(px.std()) > 0.1
    assert float(np.abs(np.diff(px, axis=0)).mean()) > 0.005


def test_report_says_what_happened(job, tmp_path):
    """Issue 13, item 13: the input and the SfM summary are shown, the water decision stands next to the mode,
    a 3dgs job says no water was removed (and shows no restored J), the header's PSNR and the curve's last point
    are either the same number or each named with its view set, and no absolute path is left."""
    job_dir, results = job
    r = _report(job_dir)
    assert r["input"] == {"name": "images", "images": 12, "skipped": 0}
    sfm = results["sfm"]
    assert r["sfm"]["registered"] == sfm["registered"] == 12 and r["sfm"]["total"] == 12
    assert r["sfm"]["matcher"] == sfm["matcher"] and r["sfm"]["mean_reproj_error_px"] == sfm["mean_reproj_error_px"]
    assert r["sfm"]["outcome"] == "single" and r["sfm"]["other_models"] == [] and r["sfm"]["unregistered"] == []
    assert r["sfm"]["pairs_matched"] == sfm["pairs_matched"] >= 11  # 12 views in one model: at least a chain
    text = JobLayout(job_dir).report_json.read_text()
    assert str(job_dir.parent) not in text and '"/' not in text  # no absolute path anywhere (options.source ...)
    html = JobLayout(job_dir).report_html.read_text()
    assert f"registered <b>{sfm['registered']} of {sfm['total']}</b>" in html and "matching" in html
    assert "Input <b>images</b>: 12 images" in html
    selection = html[html.index("<h2>Model selection</h2>"):html.index("<h2>Held-out views</h2>")]
    assert f"Water classified <b>{r['water']['water_type']}</b>" in selection
    assert f"held-out PSNR ({r['metrics']['test']['n_views']} views)" in html
    assert "the header's held-out PSNR" in html  # the curve's last point is related to the header, either way

    copy = JobLayout(tmp_path / "job3dgs")
    shutil.copytree(job_dir, copy.root, ignore=shutil.ignore_patterns("report.*", copy.curve_png.name))
    ev = json.loads(copy.evaluate.read_text())
    atomic_write_json(copy.evaluate, {**ev, "mode": "3dgs"})
    sel = {"requested": "auto", "chosen": "3dgs", "reason": "probe: the water changes nothing measurable"}
    copy.selection.write_text(json.dumps(sel))
    copy.source_name.write_text(json.dumps({"name": "reef-dive.zip"}))
    atomic_write_json(copy.restore_result, {"mode": "3dgs", "restored": 0, "note": NOTHING_TO_RESTORE, "views": []})
    write_report(copy.root, copy.output)
    r3 = json.loads(copy.report_json.read_text())
    validate_report(r3)
    assert r3["mode"] == "3dgs" and r3["input"]["name"] == "reef-dive.zip"
    html3 = copy.report_html.read_text()
    assert "No water was removed" in html3 and "probe: the water changes nothing measurable" in html3
    assert f"No photo was restored.</b> {NOTHING_TO_RESTORE}" in html3 and r3["restore"]["restored"] == 0
    assert r3["consistency"] == {"defined": False, "reason": NOTHING_TO_RESTORE}
    assert "Colour agreement across distances (no ground truth needed)" in html
    assert "Held-out views: photo, model, ground truth" in html3
    for claim in ("<figcaption>restored J", "restored J PSNR", "restored J vs true"):  # shown for dualphys
        assert claim in html and claim not in html3, claim


def test_export_writes_the_spz_beside_the_ply(job, record_property):
    """The job's reconstruction.spz holds the PLY's Gaussians within the format's quantisation, several times
    smaller (tests/splat/test_spz.py has the bounds' derivation and the reference cross-check)."""
    import torch

    from pipeline.splat.ply import read_ply
    from pipeline.splat.spz import read_spz, spz_header

    job_dir, results = job
    layout = JobLayout(job_dir)
    ply, spz = layout.ply.read_bytes(), layout.spz.read_bytes()
    assert results["export"][layout.spz.name] == len(spz)
    p, s = read_ply(ply), read_spz(spz)
    head = spz_header(spz)
    assert (head["version"], head["num_points"]) == (3, len(p["means"]))
    # a medium mode renders and stores SH up to degree 1 (MediumConfig.max_sh_degree); the SPZ keeps the PLY's
    assert head["sh_degree"] == 1 and tuple(p["shN"].shape[1:]) == (3, 3)
    ratio = len(ply) / len(spz)
    record_property("spz_ratio", round(ratio, 2))
    assert ratio > 5.0
    assert (s["means"] - p["means"]).abs().max() <= 0.5 / 2 ** head["fractional_bits"] + 1e-5
    assert (torch.sigmoid(s["opacities"]) - torch.sigmoid(p["opacities"])).abs().max() <= 0.5 / 255 + 1e-6
    assert (s["scales"] - p["scales"].clamp(-10, 255 / 16 - 10)).abs().max() <= 1 / 32 + 1e-5


def test_quality_names_the_runs_cap_when_it_is_above_the_budget():
    """An explicit mode densifies up to the preset's cap, past the pixel budget the count is judged against: the
    report says both, so 89,901 Gaussians against a budget of 56,763 does not read as a fault."""
    from pipeline.export.report_html import _quality

    q = {"n_gaussians": 89_901, "budget": 56_763, "cap": 100_000, "coverage_min": 1.0, "warnings": []}
    assert "(budget 56,763; the run&#x27;s cap 100,000)" in _quality(q)  # the line is HTML-escaped
    assert "(budget 56,763)" in _quality({**q, "cap": 56_763})
    assert "(budget 56,763)" in _quality({k: v for k, v in q.items() if k != "cap"})  # jobs from before the cap


def test_selection_says_how_much_the_photos_drift_with_range():
    """The photos' own drift (the auto mode's no-water test) is a sentence in report.html; undefined, with why."""
    from pipeline.export.report_html import _selection

    r = {"mode": "3dgs", "water": None, "selection": {"mode": "3dgs", "reason": "the photos show no water",
                                                      "drift": {"defined": True, "score": 0.004}}}
    html = _selection(r)
    assert "changes between near and far sightings by 0.004 of the seabed's contrast" in html
    r["selection"]["drift"] = {"defined": False, "score": 0.02, "reason": "the sightings' ranges span only 1.05x"}
    assert "not used: the sightings&#x27; ranges span only 1.05x" in _selection(r)
    r["selection"].pop("drift")
    assert "near and far" not in _selection(r)
