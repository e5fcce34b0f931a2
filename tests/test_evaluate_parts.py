"""Pieces of the evaluate stage: the speed-vs-error curve, its schedule, finding ground truth, and rendering a
model from the true cameras after a similarity alignment."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.evaluate import json_safe, speed_vs_error
from pipeline.ground_truth import GroundTruthError, find_ground_truth
from pipeline.scene.align import fit_similarity, umeyama, view_in_estimated_frame
from pipeline.scene.types import Camera, Scene, View
from pipeline.train_hooks import curve_every, curve_subset


def test_curve_keeps_points_strictly_increasing_in_time_and_flags_the_final_model():
    hist = [{"iteration": 10, "elapsed_s": 1.0, "psnr": 15.0}, {"iteration": 20, "elapsed_s": 2.5, "psnr": 18.0},
            {"iteration": 20, "elapsed_s": 2.5, "psnr": 18.0},  # a repeated point (never drawn backwards)
            {"iteration": 30, "elapsed_s": 3.1, "psnr": 19.5}]
    c = speed_vs_error(hist, final_iteration=30, views=["a.png"])
    assert [p["iteration"] for p in c["points"]] == [10, 20, 30]
    assert c["includes_final"] is True
    assert speed_vs_error(hist[:2], final_iteration=30, views=[])["includes_final"] is False


@pytest.mark.parametrize("iterations", [7, 150, 1500, 3000, 30_000])
def test_curve_schedule_gives_about_eight_points_ending_at_the_last_iteration(iterations):
    every = curve_every(iterations)
    # the eval hook fires at multiples of `every` and at the last iteration
    its = sorted({i for i in range(every, iterations + 1, every)} | {iterations})
    assert 7 <= len(its) <= 9 or (iterations < 8 and len(its) == iterations)
    assert its[-1] == iterations


def test_curve_views_are_a_few_evenly_spaced_held_out_views():
    assert curve_subset(2) == [0, 1]
    assert curve_subset(7) == [0, 3, 6]
    assert curve_subset(1) == [0] and curve_subset(0) == []


def test_json_safe_replaces_infinite_scores():
    out = json_safe({"psnr": float("inf"), "xs": (1.0, float("nan")), "n": 3})
    assert out == {"psnr": None, "xs": [1.0, None], "n": 3}
    json.dumps(out, allow_nan=False)


def test_ground_truth_is_found_only_in_a_generated_scene(tmp_path):
    scene = tmp_path / "scene"
    for d in ("images", "clean", "sparse_gt"):
        (scene / d).mkdir(parents=True)
    (scene / "water.json").write_text(json.dumps({"beta_D": [0.5, 0.2, 0.1], "generator": {"views": 3}}))
    assert find_ground_truth(scene / "images") == scene
    assert find_ground_truth(scene / "images", explicit=scene) == scene
    assert find_ground_truth(tmp_path / "upload.zip") is None
    other = tmp_path / "photos" / "images"
    other.mkdir(parents=True)
    assert find_ground_truth(other) is None
    with pytest.raises(GroundTruthError):
        find_ground_truth(scene / "images", explicit=tmp_path / "photos")


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_true_cameras_carried_into_an_estimated_world_see_the_same_points():
    rng = np.random.default_rng(0)
    cam = Camera(80, 60, 70.0, 70.0, 40.0, 30.0)
    true_views = [View(f"f{i}.png", cam, _rot(rng.normal(size=3), 0.3), rng.normal(size=3)) for i in range(5)]
    # An "SfM" world: x_est = (R_s^T (x_true - t_s)) / s, i.e. x_true = s R_s x_est + t_s.
    s, R_s, t_s = 0.25, _rot(np.array([0.2, 1.0, -0.4]), 1.1), np.array([3.0, -1.0, 0.5])
    est_views = []
    for v in true_views:
        R = v.R @ R_s
        est_views.append(View(v.name, cam, R, (v.R @ t_s + v.t) / s))
    sim = fit_similarity(Scene(est_views), Scene(true_views))
    assert sim.scale == pytest.approx(s, rel=1e-9)
    x_true = rng.normal(size=(20, 3)) + np.array([0, 0, 4.0])
    x_est = ((x_true - t_s) @ R_s) / s  # R_s^T (x - t) for each row
    for v in true_views:
        mapped = view_in_estimated_frame(v, sim)
        cam_true = x_true @ v.R.T + v.t
        cam_est = x_est @ mapped.R.T + mapped.t
        np.testing.assert_allclose(cam_est * s, cam_true, atol=1e-9)  # same rays; depth in estimated units
    s2, _, _ = umeyama(np.stack([v.center for v in est_views]), np.stack([v.center for v in true_views]))
    assert s2 == pytest.approx(s, rel=1e-9)
