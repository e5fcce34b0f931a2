"""The survey's records in a generated photo-family scene (``pipeline.synth.survey_records``, ``.exif_records``,
``.geo``): EXIF SubjectDistance against the true camera-to-bottom distance, GPS positions that convert back to the
true camera centres, capture times, pixels untouched by the EXIF, and the CLI flags."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pyproj import Geod

from pipeline.scene.colmap import read_colmap
from pipeline.scene.images import read_pixels, write_image
from pipeline.synth.exif_records import ExifRecord, read_records, write_exif
from pipeline.synth.geo import WorldGeo, utm_epsg
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene, photo_views
from pipeline.synth.procedural import to_u8
from pipeline.synth.survey_records import COLUMNS, RECORDS_FILE, read_records_csv

ORIGIN = (-9.5988, 143.7811)  # AIMS Erub, Torres Strait (UTM zone 54 S)
SURVEY = PhotoSynthConfig(views=6, width=160, height=120, seed=3, grid_size=512, n_points=200, supersample=1,
                          gps_origin=ORIGIN, altimeter_noise=0.02, capture_start="2023-03-20T01:22:53")
EXACT = replace(SURVEY, views=3, width=48, height=36, seed=4, gps_origin=None, altimeter_noise=0.0)


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    return generate_photo_scene(SURVEY, tmp_path_factory.mktemp("survey"))


def _rows(root: Path) -> list[dict]:
    with (root / RECORDS_FILE).open(newline="") as f:
        return list(csv.DictReader(f))


def _centres(root: Path) -> dict[str, np.ndarray]:
    return {v.name: v.center for v in read_colmap(root / "sparse_gt", root / "images").views}


def test_subject_distance_is_the_true_axis_range_within_the_altimeter_noise(survey):
    rows = _rows(survey)
    assert list(rows[0]) == list(COLUMNS) and [r["file"] for r in rows] == [f"frame_{i:04d}.png" for i in range(6)]
    ratios = []
    for r in rows:
        exif = read_records(survey / "images" / r["file"])
        true = float(r["true_camera_to_bottom_m"])
        assert exif["subject_distance_m"] == pytest.approx(float(r["camera_to_bottom_m"]), abs=1e-6)
        ratios.append(exif["subject_distance_m"] / true)
        # The true range is the depth map's camera z at the principal point, the corner of the 4 centre pixels:
        # their mean is within the relief's variation over their 3 cm footprint (0.7 % in an oblique view).
        z = np.load(survey / "depth" / f"{Path(r['file']).stem}.npy")
        assert true == pytest.approx(float(z[59:61, 79:81].mean()), rel=0.01)
    dev = np.abs(np.array(ratios) - 1)
    assert dev.max() < 5 * SURVEY.altimeter_noise and dev.max() > 1e-3  # noisy, but within 5 sigma


def test_without_noise_subject_distance_equals_the_truth_and_no_gps_means_no_gps_tags(tmp_path):
    root = generate_photo_scene(EXACT, tmp_path / "exact")
    for rec in read_records_csv(root):
        exif = read_records(root / "images" / rec.file)
        assert rec.camera_to_bottom_m == rec.true_camera_to_bottom_m
        assert exif["subject_distance_m"] == pytest.approx(rec.true_camera_to_bottom_m, abs=1e-9)
        assert exif["lat"] is None and exif["lon"] is None and rec.lat is None
        with Image.open(root / "images" / rec.file) as im:
            assert 0x8825 not in im.getexif()
    assert json.loads((root / "water.json").read_text())["survey_records"]["gps"] is None


def test_gps_converts_back_to_the_true_camera_centres(survey):
    geo = WorldGeo(SURVEY.gps_origin)
    assert geo.crs == "EPSG:32754"  # 143.78° E, south of the equator
    centres = _centres(survey)
    for r in _rows(survey):
        exif = read_records(survey / "images" / r["file"])
        assert exif["lat"] == pytest.approx(float(r["lat"]), abs=1e-9)  # 1e-6″ rationals
        assert exif["lon"] == pytest.approx(float(r["lon"]), abs=1e-9)
        x, y = geo.world_xy(exif["lat"], exif["lon"])
        np.testing.assert_allclose([x, y], centres[r["file"]][:2], atol=0.01)
    meta = json.loads((survey / "water.json").read_text())["survey_records"]["gps"]
    assert meta["crs"] == "EPSG:32754" and meta["origin_lat_lon"] == list(ORIGIN)


def test_world_x_is_east_and_y_north_in_ground_metres():
    """Independent of the inverse: geodesic distance and azimuth from the origin (WGS 84 ellipsoid) to world
    points; UTM grid metres differ from ground metres by the point scale factor (< 0.1 % inside a zone) and grid
    north from true north by the convergence (about 0.3° here, 0.4° from the zone's central meridian)."""
    geo = WorldGeo(ORIGIN)
    lat, lon = geo.latlon(np.array([0.0, 100.0, 0.0, -30.0]), np.array([0.0, 0.0, 100.0, -40.0]))
    np.testing.assert_allclose([lat[0], lon[0]], ORIGIN, atol=1e-9)
    az, _, dist = Geod(ellps="WGS84").inv(np.full(3, ORIGIN[1]), np.full(3, ORIGIN[0]), lon[1:], lat[1:])
    np.testing.assert_allclose(dist, [100.0, 100.0, 50.0], rtol=1e-3)
    np.testing.assert_allclose(az, [90.0, 0.0, -180 + np.degrees(np.arctan2(30, 40))], atol=1.0)
    assert utm_epsg(51.5, -0.1) == 32630 and utm_epsg(-33.9, 151.2) == 32756
    with pytest.raises(ValueError, match="UTM"):
        WorldGeo((85.0, 0.0))


def test_capture_times_step_by_the_interval_and_other_readers_agree(survey):
    from service.surveys.exif import read_exif_time

    start = datetime(2023, 3, 20, 1, 22, 53, tzinfo=UTC)
    for i, r in enumerate(_rows(survey)):
        path = survey / "images" / r["file"]
        t = read_records(path)["time"]
        assert (t - start).total_seconds() == pytest.approx(i * SURVEY.capture_interval, abs=1e-6)
        assert read_exif_time(path) == pytest.approx(t.timestamp(), abs=1e-6)  # the survey folders' reader
        assert r["datetime"] == t.strftime("%Y:%m:%d %H:%M:%S") + f".{t.microsecond // 1000:03d}"


def test_written_pixels_are_the_rendered_ones(survey):
    """The EXIF changes no pixel: images/ decode to exactly the 8-bit rendering (OpenImageIO and Pillow)."""
    _, views = photo_views(SURVEY)
    for sv in views:
        path = survey / "images" / sv.view.name
        expected = to_u8(sv.image)
        with Image.open(path) as im:
            assert np.array_equal(np.asarray(im.convert("RGB")), expected)
        assert np.array_equal(np.round(read_pixels(path) * 255).astype(np.uint8), expected)
        assert read_records(path)["subject_distance_m"] is not None


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_write_exif_keeps_the_file_apart_from_its_exif_and_replaces_old_records(tmp_path, suffix):
    rng = np.random.default_rng(0)
    path = write_image(tmp_path / f"a{suffix}", rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
    before_bytes, before = path.read_bytes(), read_pixels(path)
    t = datetime(2024, 1, 2, 3, 4, 5, 678000, tzinfo=UTC)
    write_exif(path, ExifRecord(t, 2.5, 51.5, -0.125))
    write_exif(path, ExifRecord(t, 1.25, -33.875, 151.25))  # replaces, never stacks
    assert np.array_equal(read_pixels(path), before)
    data = path.read_bytes()
    assert data.count(b"eXIf" if suffix == ".png" else b"Exif\x00\x00") == 1
    tail = b"IDAT" if suffix == ".png" else b"\xff\xda"  # the pixel data onwards is the same bytes
    assert data[data.index(tail):] == before_bytes[before_bytes.index(tail):]
    rec = read_records(path)
    assert rec["time"] == t and rec["subject_distance_m"] == 1.25 and rec["gps_altitude_m"] is None
    assert rec["lat"] == pytest.approx(-33.875, abs=1e-10) and rec["lon"] == pytest.approx(151.25, abs=1e-10)
    write_exif(path, ExifRecord(t, None, None, None))  # no altimeter, no GPS
    rec = read_records(path)
    assert rec["subject_distance_m"] is None and rec["lat"] is None and rec["time"] == t


def test_real_aims_frame_reads_as_its_frames_csv():
    """The reader against a real ReefScan frame (the layout this module copies) and its survey's own list."""
    folder = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "aims-erub-mt81"
    with (folder / "frames.csv").open(newline="") as f:
        row = next(csv.DictReader(f))
    rec = read_records(folder / "images" / row["file"])
    assert rec["subject_distance_m"] == pytest.approx(float(row["camera_to_bottom_m"]), abs=1e-9)
    assert rec["lat"] == pytest.approx(float(row["lat"]), abs=2e-7)  # frames.csv rounds to 1e-7°
    assert rec["lon"] == pytest.approx(float(row["lon"]), abs=2e-7)
    assert rec["time"].strftime("%Y:%m:%d %H:%M:%S") == row["datetime"]


def test_cli_gps_and_altimeter_flags_survive_the_camera_effects(tmp_path, capsys):
    from cli.main import main

    out = tmp_path / "cli"
    assert main(["synth", "--family", "photo", "--out", str(out), "--views", "3", "--size", "48x36",
                 "--gps=-9.5988,143.7811", "--altimeter-noise", "-1", "--fall-off", "0.3"]) == 0
    gen = json.loads((out / "water.json").read_text())["generator"]
    assert gen["gps_origin"] == [-9.5988, 143.7811] and gen["altimeter_noise"] == -1
    for row in _rows(out):
        rec = read_records(out / "images" / row["file"])  # fall-off rewrote images/; the records were restamped
        assert rec["subject_distance_m"] is None and row["camera_to_bottom_m"] == ""
        assert rec["lat"] == pytest.approx(float(row["lat"]), abs=1e-9)
    assert main(["synth", "--out", str(tmp_path / "p"), "--gps", "1,2"]) == 2  # photo family only
    with pytest.raises(SystemExit):
        main(["synth", "--family", "photo", "--out", str(tmp_path / "q"), "--gps", "95,0"])
    capsys.readouterr()


def test_records_csv_columns_match_the_real_survey_list():
    """records.csv names its columns as AIMS's frames.csv does (plus the truth)."""
    folder = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "aims-erub-mt81"
    real = (folder / "frames.csv").read_text().splitlines()[0].split(",")
    assert set(COLUMNS) - set(real) == {"true_camera_to_bottom_m"}
