"""Pieces of the evaluate stage: the speed-vs-error curve, its schedule, finding ground truth, and rendering a
model from the true cameras after a similarity alignment."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.config import SynthConfig
from pipeline.evaluate.evaluation import channel_bias, json_safe, speed_vs_error
from pipeline.scene.align import fit_similarity, umeyama, view_in_estimated_frame
from pipeline.scene.records import Camera, Scene, View, scaled_view
from pipeline.synth.ground_truth import FAR_DEPTH_M, GroundTruthError, find_ground_truth, load_ground_truth
from pipeline.synth.procedural import generate_scene
from pipeline.train.hooks import curve_every, curve_subset


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


def test_channel_bias_is_the_mean_error_per_channel():
    clean = np.random.default_rng(0).uniform(0.2, 0.6, (12, 16, 3))
    veil = clean + np.array([0.0, 0.05, -0.02])  # a flat green veil left on, blue taken off
    assert channel_bias(veil, clean) == pytest.approx([0.0, 0.05, -0.02], abs=1e-4)
    assert channel_bias(clean, clean) == [0.0, 0.0, 0.0]


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


@pytest.fixture(scope="module")
def small_truth(tmp_path_factory):
    root = tmp_path_factory.mktemp("gt")
    generate_scene(SynthConfig(views=8, width=80, height=60, preset="medium", seed=0), root)
    return load_ground_truth(root)


def test_a_view_sees_its_own_surface_and_nothing_else(small_truth):
    gt = small_truth
    v = gt.scene.views[3]
    surface = gt.depth(v) < FAR_DEPTH_M
    (own,) = gt.seen_by([v], [v])
    assert surface.any() and not (own & ~surface).any()
    assert own[surface].mean() > 0.99  # pixel centres project back to themselves at their own depth
    assert not gt.seen_by([v], [])[0].any()
    # At the training resolution (downscale 2) the same surface is seen from the full-size view.
    assert gt.seen_by([scaled_view(v, 2)], [v])[0][gt.depth(scaled_view(v, 2)) < FAR_DEPTH_M].mean() > 0.97


def test_seen_by_is_a_union_over_views_and_checks_occlusion(small_truth):
    gt = small_truth
    v, others = gt.scene.views[0], gt.scene.views[1:]
    each = [gt.seen_by([v], [o])[0] for o in others]
    (union,) = gt.seen_by([v], others)
    np.testing.assert_array_equal(union, np.logical_or.reduce(each))
    assert 0.2 < union.mean() < 1.0  # neighbours overlap frame 0 but do not cover all of it
    # The same view moved 1 m back along its axis: every surface point still projects inside its frame, but at
    # 1 m more than its depth map says, so the depth test (a hidden point) must refuse them all.
    o = gt.scene.views[3]
    moved = View(o.name, o.camera, o.R, o.t + np.array([0.0, 0.0, 1.0]), o.image_path)
    u, w, _ = moved.project(np.array([o.center + o.R[2] * 3.0]))
    assert 0 <= u[0] < o.camera.width and 0 <= w[0] < o.camera.height
    assert gt.seen_by([o], [o])[0].mean() > 0.5 and not gt.seen_by([o], [moved])[0].any()
