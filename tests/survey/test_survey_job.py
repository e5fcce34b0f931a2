"""Issue 42 at test size: a generated survey with a ±2 % altimeter and GPS in its photos' EXIF, one whole job, and
its products against the generator's truth: the scale, the de-watered orthomosaic against the true seabed colour on
the same grid, its planimetric error at checkpoints, the elevation model's error, the georeference and the files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from pipeline.export.report import build_report, validate_report
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, parse_scale_bars
from pipeline.job.runner import run_job
from pipeline.restore.views import lens_cameras
from pipeline.survey.geotiff import validate_cog
from pipeline.survey.marks import bar_length_units
from pipeline.survey.surface import render_depths
from pipeline.synth.ground_truth import load_ground_truth
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import model_from_state, training_views

pytestmark = pytest.mark.slow

GPS = (-9.5988, 143.7811)  # AIMS Erub's line: UTM zone 54S


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    root = tmp_path_factory.mktemp("survey")
    scene = generate_photo_scene(PhotoSynthConfig(views=16, width=400, height=300, preset="medium", seed=0,
                                                  gps_origin=GPS), root / "scene")
    run_job(root / "job", JobOptions(source=str(scene / "images"), mode="homogeneous", iterations=600,
                                     max_width=200, colour_space="srgb"))
    layout = JobLayout(root / "job")
    return layout, json.loads(layout.survey_result.read_text())


def test_scale_from_the_altimeter_within_2_percent(job):
    _, s = job
    assert s["scale"]["source"] == "altimeter" and s["scale"]["frames"] >= 12
    assert abs(s["truth"]["scale_error"]) < 0.02, s["truth"]


def test_orthomosaic_as_good_as_the_restored_photos(job, record_property):
    _, s = job
    t = s["truth"]
    record_property("ortho", t)
    assert t["ortho_minus_photos_db"] > -1.0, t
    # checkpoints within 2 ground pixels: measured median 0.7, worst 1.1 (the worst bounded at 4: runs differ)
    r = t["restored"]
    assert r["checkpoints"] >= 8 and r["planimetric_px_median"] <= 2.0 and r["planimetric_px_max"] <= 4.0, r
    assert t["water"]["psnr"] < t["restored"]["psnr"] - 3  # the water was there, and it came off


def test_elevation_error_stays_at_the_rendered_depths_own(job):
    """Measured at this size: median 1.0 %, RMS 2.3 % of the camera-to-bottom distance — the rendered depth's own
    error; issue 42 asks for an RMS of 0.5 %, which this DEM does not reach (its note). The bounds catch a DEM that
    loses what the spread weights, despeckling and the well-seen mask bought (RMS 19 % without them)."""
    _, s = job
    e = s["truth"]["elevation"]
    assert e["median_abs_share_of_range"] <= 0.025 and e["rmse_share_of_range"] <= 0.08, e
    t = s["truth"]["terrain"]
    assert abs(t["rugosity"] / t["rugosity_true"] - 1) < 0.3, t


def test_products_are_valid_cogs_in_utm_54s_and_in_the_report(job):
    layout, s = job
    assert s["frame"]["georeferenced"] and s["frame"]["crs"] == "EPSG:32754", s["frame"]
    for path in (layout.ortho, layout.ortho_water, layout.ortho_confidence, layout.dem):
        ok, errors, _ = validate_cog(path)
        assert ok, (path, errors)
        with rasterio.open(path) as ds:
            assert ds.crs.to_epsg() == 32754 and ds.res[0] == pytest.approx(s["grid"]["gsd"])
            assert ds.width == s["grid"]["width"] and ds.overviews(1) or ds.width < 512
    with rasterio.open(layout.dem) as ds:
        dem = ds.read(1)
    assert np.isfinite(dem).mean() > 0.25 and np.nanstd(dem) > 0.01  # relief in metres, nodata outside
    assert 1.0 < s["terrain"]["rugosity"] < 1.5
    for p in (layout.ortho_preview, layout.ortho_water_preview, layout.hillshade_preview):
        assert p.stat().st_size > 1000
    report = build_report(layout.root)
    validate_report(report)
    assert report["survey"]["scale"]["source"] == "altimeter"
    assert report["model"]["metres_per_unit_source"].startswith("ground truth")


def test_a_scale_bar_marked_in_a_photo_gives_the_true_scale(job):
    """Two pixels of one photo, 100 px apart, and their true distance on the seabed (the generator's depth and
    camera): the bar's scale matches the alignment's true scale within 2 %."""
    layout, s = job
    gt = load_ground_truth(Path(JobOptions.from_json(json.loads(layout.options.read_text())).source).parent)
    state = load_checkpoint(layout.checkpoint)
    model = model_from_state(state)
    views = training_views(layout.root, state)
    name = views[len(views) // 2].name
    depths = {vd.view.name: vd for vd in render_depths(model, [v for v in views if v.name == name])}
    true_view = next(v for v in gt.scene.views if v.name == name)
    depth = np.load(gt.root / "depth" / f"{Path(name).stem}.npy")
    c = true_view.camera
    (x1, y1), (x2, y2) = (150, 150), (250, 150)

    def world(x, y):
        z = float(depth[y, x])
        cam = np.array([(x + 0.5 - c.cx) / c.fx * z, (y + 0.5 - c.cy) / c.fy * z, z])
        return true_view.R.T @ (cam - true_view.t)

    metres = float(np.linalg.norm(world(x1, y1) - world(x2, y2)))
    (bar,) = parse_scale_bars(f"{name}:{x1},{y1}:{x2},{y2}:{metres}")
    _, units = bar_length_units(bar, depths, lens_cameras(layout.scene))
    assert metres / units == pytest.approx(s["truth"]["true_metres_per_unit"], rel=0.02)
