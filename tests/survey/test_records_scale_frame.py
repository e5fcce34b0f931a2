"""The survey's records (EXIF, telemetry CSV), the metric scale from them and the map frame (plane, UTM fit)."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.ingest.intake import ingest
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, parse_scale_bars
from pipeline.survey.frame import fit_plane, georeference, heading_sigma_deg, plane_frame, utm_epsg
from pipeline.survey.measure import resolve_telemetry
from pipeline.survey.records import FrameRecord, exif_record, frame_records, read_telemetry
from pipeline.survey.scale import altimeter_scale, choose_scale

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
ERUB = REAL / "aims-erub-mt81"


def test_aims_exif_gives_the_altimeter_gps_and_time_as_frames_csv_lists_them():
    rows = list(csv.DictReader(open(ERUB / "frames.csv")))
    for row in rows[:5]:
        rec = exif_record(ERUB / "images" / row["file"])
        assert rec.distance_m == pytest.approx(float(row["camera_to_bottom_m"]), abs=1e-6)
        assert rec.lat == pytest.approx(float(row["lat"]), abs=2e-7)  # EXIF's seconds carry 3 decimals (3 cm)
        assert rec.lon == pytest.approx(float(row["lon"]), abs=2e-7)
        assert rec.time == row["datetime"] and rec.source == "exif"


def test_a_photo_without_records_and_an_unreadable_file_give_an_empty_record(tmp_path):
    bad = tmp_path / "x.jpg"
    bad.write_bytes(b"not a jpeg")
    assert exif_record(bad) == FrameRecord()


def test_telemetry_rows_match_flattened_names_and_win_over_exif(tmp_path):
    csv_path = tmp_path / "log.csv"
    csv_path.write_text("Filename,Altitude_m,Latitude,Longitude\n20230320_012253_000_0001.jpg,2.5,-9.6,143.78\n")
    table = read_telemetry(csv_path)
    assert table["20230320_012253_000_0001.jpg"].distance_m == 2.5
    image = ERUB / "images" / "20230320_012253_000_0001.jpg"
    recs = frame_records({"sub__20230320_012253_000_0001.jpg": image}, csv_path)
    r = recs["sub__20230320_012253_000_0001.jpg"]
    assert r.distance_m == 2.5 and r.lat == -9.6 and r.source == "exif+telemetry"
    assert r.time == "2023:03:20 01:22:53"  # EXIF's where the log has none


def test_a_csv_without_a_file_column_is_refused_with_the_reason(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="file-name column"):
        read_telemetry(p)


def test_altimeter_scale_is_the_median_ratio_and_names_the_outlier():
    rng = np.random.default_rng(0)
    units = {f"f{i}": float(u) for i, u in enumerate(rng.uniform(4, 6, 30))}
    alt = {n: u * 0.4 * (1 + rng.normal(0, 0.02)) for n, u in units.items()}
    alt["f3"] = units["f3"] * 0.4 * 1.5  # a bad reading
    fit = altimeter_scale(alt, units)
    assert fit.metres_per_unit == pytest.approx(0.4, rel=0.01)
    assert fit.outliers == ["f3"] and fit.frames == 29
    assert 0.01 < fit.spread < 0.03
    assert choose_scale(fit, None, 0.9).source == "altimeter"


def test_scale_sources_fall_back_in_order_and_say_so():
    noisy = altimeter_scale({f"f{i}": 1.0 + (i % 2) for i in range(6)}, {f"f{i}": 1.0 for i in range(6)})
    chosen = choose_scale(noisy, None, 0.25)
    assert chosen.source == "metric_scale" and chosen.metres_per_unit == 0.25 and "disagree" in chosen.note
    assert choose_scale(None, None, None, 0.5).source == "gps"
    none = choose_scale(None, None, None)
    assert none.metres_per_unit is None and "arbitrary" in none.note


def test_scale_bar_text_is_parsed_and_bad_text_refused():
    (bar,) = parse_scale_bars("a b.jpg:10,20:110,20.5:0.5")
    assert bar.photo == "a b.jpg" and bar.a == (10, 20) and bar.b == (110, 20.5) and bar.metres == 0.5
    assert len(parse_scale_bars("a.jpg:1,2:3,4:1; b.jpg:1,2:5,6:2")) == 2
    for bad in ("a.jpg:1,2:3,4", "a.jpg:1,2:1,2:1", "a.jpg:1,2:3,4:-1", ":1,2:3,4:1"):
        with pytest.raises(ValueError, match="scale_bar"):
            parse_scale_bars(bad)


def _tilted_scene(rng):
    """Points on a plane tilted 20° with 5 % stray points, cameras 3 units above it."""
    R = np.array([[1, 0, 0], [0, np.cos(0.35), -np.sin(0.35)], [0, np.sin(0.35), np.cos(0.35)]])
    pts = np.c_[rng.uniform(-5, 5, (500, 2)), rng.normal(0, 0.02, 500)]
    pts[:25, 2] += rng.uniform(1, 2, 25)  # floaters
    cams = np.c_[np.linspace(-4, 4, 12), np.zeros(12), np.full(12, 3.0)]
    return pts @ R.T + [1, 2, 3], cams @ R.T + [1, 2, 3], R


def test_plane_fit_ignores_stray_points_and_up_points_to_the_cameras():
    rng = np.random.default_rng(1)
    pts, cams, R = _tilted_scene(rng)
    _, n = fit_plane(pts)
    assert abs(abs(n @ R[:, 2]) - 1) < 1e-3
    frame = plane_frame(pts, cams, 0.5)
    m = frame.to_map(cams)
    assert np.allclose(m[:, 2], 1.5, atol=0.02)  # 3 units above the plane at 0.5 m per unit
    assert np.allclose(frame.to_world(frame.to_map(pts)), pts)


def test_gps_fit_turns_the_frame_to_utm_and_a_poor_fit_keeps_the_local_frame():
    import pyproj

    rng = np.random.default_rng(2)
    pts, cams, _ = _tilted_scene(rng)
    local = plane_frame(pts, cams, 0.5)
    lat0, lon0 = -9.5988, 143.7811
    epsg = utm_epsg(lat0, lon0)
    assert epsg == 32754  # WGS 84 / UTM zone 54S (Torres Strait)
    fwd = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    inv = pyproj.Transformer.from_crs(epsg, 4326, always_xy=True)
    e0, n0 = fwd.transform(lon0, lat0)
    theta = np.radians(30)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    xy = local.to_map(cams)[:, :2] @ rot.T + [e0, n0]
    lon, lat = inv.transform(xy[:, 0], xy[:, 1])
    names = {f"c{i}": c for i, c in enumerate(cams)}
    recs = {f"c{i}": FrameRecord(lat=la, lon=lo) for i, (la, lo) in enumerate(zip(lat, lon))}
    fit = georeference(local, names, recs, scale_known=True)
    assert fit.georeferenced and fit.frame.epsg == 32754 and "UTM zone 54S" in fit.frame.crs_name
    assert fit.residual_m < 0.01 and fit.heading_sigma_deg < 0.5
    assert heading_sigma_deg(np.c_[np.linspace(0, 1.5, 19), np.zeros(19)], 0.8) > 10  # Ugar's: 1.5 m of track
    assert np.allclose(fit.frame.to_map(cams)[:, :2], xy, atol=0.01)
    # a boat's GPS wandering metres off the camera track: not a fit, the local frame stays
    wander = xy + rng.normal(0, 3.0, xy.shape)
    lon, lat = inv.transform(wander[:, 0], wander[:, 1])
    recs = {f"c{i}": FrameRecord(lat=la, lon=lo) for i, (la, lo) in enumerate(zip(lat, lon))}
    poor = georeference(local, names, recs, scale_known=True)
    assert not poor.georeferenced and poor.frame.epsg is None and "does not fit" in poor.note


def test_ingest_keeps_the_survey_log_and_the_options_find_it_by_name(tmp_path):
    src = tmp_path / "line"
    (src / "sub").mkdir(parents=True)
    for p in sorted((ERUB / "images").glob("*.jpg"))[:3]:
        shutil.copyfile(p, src / p.name)
    shutil.copyfile(ERUB / "frames.csv", src / "sub" / "frames.csv")
    (src / "notes.txt").write_text("not a record")
    job = JobLayout(tmp_path / "job")
    ingest(src, job.root)
    assert sorted(p.name for p in job.records.iterdir()) == ["sub__frames.csv"]
    found = resolve_telemetry(JobOptions(source=str(src), telemetry="frames.csv"), job.records)
    assert found == job.records / "sub__frames.csv" and read_telemetry(found)
    with pytest.raises(FileNotFoundError, match="sub__frames.csv"):
        resolve_telemetry(JobOptions(source=str(src), telemetry="other.csv"), job.records)
    assert resolve_telemetry(JobOptions(source=str(src)), job.records) is None
