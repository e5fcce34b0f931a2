"""``output/cameras.json`` (``pipeline.export.cameras``): the training cameras for the dashboard's 3D viewer."""

from __future__ import annotations

import json
import math

import numpy as np

from pipeline.export.cameras import cameras_document, export_cameras
from pipeline.job.layout import JobLayout
from pipeline.scene.records import Camera, View
from service.jobs.artifacts import list_artifacts


def _view(name: str, yaw_deg: float, centre: tuple[float, float, float]) -> View:
    a = math.radians(yaw_deg)
    R = np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
    return View(name, Camera(200, 100, 100.0, 125.0, 100.0, 50.0), R, -R @ np.array(centre))


def test_each_camera_is_where_its_view_says_and_looks_at_what_it_projects():
    views = [_view("b.png", 30.0, (1.0, -0.5, 2.0)), _view("a.png", 0.0, (0.0, 0.0, 0.0))]
    means = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 3.0], [0.0, 0.0, -4.0], [0.1, 0.2, 7.0]])
    doc = cameras_document(views, means)
    assert doc["count"] == 2 and [c["name"] for c in doc["cameras"]] == ["a.png", "b.png"]
    assert math.isclose(doc["extent"], math.sqrt(1 + 0.25 + 4))
    a, b = doc["cameras"]
    assert np.allclose(b["position"], [1.0, -0.5, 2.0])
    # a point on the optical axis projects to the principal point; "up" is the image's -y
    p = np.array(b["position"]) + 3.0 * np.array(b["forward"])
    u, v, z = views[0].project(p[None])
    assert np.allclose([u[0], v[0], z[0]], [100.0, 50.0, 3.0])
    u2, v2, _ = views[0].project((p + 0.1 * np.array(b["up"]))[None])
    assert np.isclose(u2[0], 100.0) and v2[0] < 50.0
    assert np.allclose(np.array(b["rotation"]) @ np.array(b["rotation"]).T, np.eye(3))
    assert math.isclose(a["fov_x_deg"], 90.0) and math.isclose(a["fov_y_deg"], 2 * math.degrees(math.atan(0.4)))
    assert a["median_depth"] == 5.0  # of the three points in front of camera a (3, 5, 7); the one behind is left out
    assert (a["width"], a["height"], a["fx"], a["cy"]) == (200, 100, 100.0, 50.0)


def test_no_gaussian_in_front_gives_no_depth():
    doc = cameras_document([_view("a.png", 0.0, (0.0, 0.0, 0.0))], np.array([[0.0, 0.0, -1.0]]))
    assert doc["cameras"][0]["median_depth"] is None
    json.dumps(doc, allow_nan=False)  # plain JSON a browser parses


def test_cameras_json_is_a_job_artifact_once_export_is_done(tmp_path):
    layout = JobLayout(tmp_path)
    layout.output.mkdir(parents=True)
    assert export_cameras([_view("a.png", 0.0, (0.0, 0.0, 0.0))], None, layout.output / "cameras.json") == 1
    assert "output/cameras.json" not in [a.path for a in list_artifacts(tmp_path)]  # export not finished yet
    layout.markers.mkdir()
    layout.marker("export").write_text("{}")
    arts = {a.path: a for a in list_artifacts(tmp_path)}
    assert arts["output/cameras.json"].media_type == "application/json"
    assert json.loads((layout.output / "cameras.json").read_text())["cameras"][0]["median_depth"] is None
