"""The synthetic scene generator checked against closed-form truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.config import SynthConfig
from pipeline.scene.records import ray_length_factor
from pipeline.synth.procedural import generate_scene, make_camera, synth_views
from pipeline.synth.water import WATER_PRESETS


def _plane_depth(view, height_of_plane: float = 0.0) -> np.ndarray:
    """Closed-form camera-space z of the plane z_world = height_of_plane for every pixel centre."""
    cam = view.camera
    u = np.arange(cam.width) + 0.5
    v = np.arange(cam.height) + 0.5
    uu, vv = np.meshgrid(u, v)
    d_cam = np.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, np.ones_like(uu)], -1)  # z = 1
    d_world = d_cam @ view.R  # R^T d
    c = view.center
    s = (height_of_plane - c[2]) / d_world[..., 2]  # x_world = c + s·d_world, and z_cam = s
    return s


def test_flat_seabed_depth_matches_closed_form():
    cfg = SynthConfig(views=4, width=64, height=48, relief=0.0, n_rocks=0, n_corals=0, supersample=1,
                      altitude=2.5, preset="none", path="survey")
    _, views = synth_views(cfg)
    for sv in views:
        expected = _plane_depth(sv.view)
        assert np.all(expected > 0)
        np.testing.assert_allclose(sv.depth, expected, rtol=1e-6, atol=1e-6)
    # Downward views: depth ≈ altitude everywhere (attitude jitter is at most 1.5°).
    assert abs(float(np.median(views[0].depth)) - 2.5) < 2.5 * (1 - math.cos(math.radians(3))) + 0.03


def test_supersampled_flat_depth_is_the_mean_of_its_samples():
    # A plane's z is affine in pixel coordinates, so the box-filtered depth equals the pixel-centre value.
    cfg = SynthConfig(views=2, width=32, height=24, relief=0.0, n_rocks=0, n_corals=0, supersample=3,
                      preset="none", path="lawnmower")
    _, views = synth_views(cfg)
    for sv in views:
        np.testing.assert_allclose(sv.depth, _plane_depth(sv.view), rtol=1e-6)


@pytest.fixture(scope="module")
def medium_scene(tmp_path_factory):
    cfg = SynthConfig(views=6, width=80, height=60, preset="medium", seed=3, noise_std=0.0, n_points=400)
    return cfg, generate_scene(cfg, tmp_path_factory.mktemp("synth"))


def test_written_pixels_obey_the_closed_form_model(medium_scene):
    from pipeline.scene.images import read_image

    cfg, root = medium_scene
    meta = json.loads((root / "water.json").read_text())
    beta_d, beta_b, b_inf = (np.array(meta[k]) for k in ("beta_D", "beta_B", "B_inf"))
    assert meta["preset"] == "medium" and meta["units"]["beta_D"] == "1/m"
    ray = ray_length_factor(make_camera(cfg))
    for name in ("frame_0000", "frame_0005"):
        I = read_image(root / "images" / f"{name}.png")
        J = read_image(root / "clean" / f"{name}.png")
        z = np.load(root / "depth" / f"{name}.npy")
        r = (z * ray)[..., None]
        model = J * np.exp(-beta_d * r) + b_inf * (1 - np.exp(-beta_b * r))
        # Both PNGs are 8-bit: J's rounding (≤ 0.5/255, attenuated) plus I's rounding (≤ 0.5/255).
        assert np.abs(I - model).max() <= 1.0 / 255 + 1e-6
        mi, mj = I.mean(axis=(0, 1)), J.mean(axis=(0, 1))
        assert mi[0] < 0.6 * mj[0]  # red is absorbed first: the water is really there
        assert mi[1] / mi[0] > 1.5 * mj[1] / mj[0]  # and the image turns blue-green


def test_water_changes_the_image_as_physics_says():
    base = dict(views=3, width=48, height=36, seed=1, noise_std=0.0)
    _, clean = synth_views(SynthConfig(preset="none", **base))
    _, turbid = synth_views(SynthConfig(preset="turbid", **base))
    for c, t in zip(clean, turbid):
        np.testing.assert_array_equal(c.J, t.J)  # same scene, only the water differs
        np.testing.assert_allclose(c.image, c.J, atol=1e-12)  # no water: I = J
        # Contrast (std) drops and the image moves towards the veiling light.
        assert np.all(t.image.std(axis=(0, 1)) < 0.5 * c.image.std(axis=(0, 1)))  # per-channel contrast
        binf = np.array(WATER_PRESETS["turbid"].B_inf)
        assert np.abs(t.image.mean(axis=(0, 1)) - binf).sum() < np.abs(c.image.mean(axis=(0, 1)) - binf).sum()


def test_deterministic_by_seed():
    cfg = SynthConfig(views=2, width=40, height=30, seed=5)
    _, a = synth_views(cfg)
    _, b = synth_views(cfg)
    _, c = synth_views(SynthConfig(views=2, width=40, height=30, seed=6))
    np.testing.assert_array_equal(a[1].image, b[1].image)
    assert np.abs(a[1].J - c[1].J).mean() > 0.01


def test_sparse_gt_is_a_consistent_colmap_model(medium_scene):
    from pipeline.scene.colmap import read_colmap

    cfg, root = medium_scene
    scene = read_colmap(root / "sparse_gt", root / "images")
    assert len(scene.views) == cfg.views
    cam = scene.views[0].camera
    assert (cam.width, cam.height) == (cfg.width, cfg.height)
    assert math.isclose(cam.fx, make_camera(cfg).fx, rel_tol=1e-9)
    assert len(scene.points) > 200
    # Every true point lies in front of the cameras that observe it; reprojection of the surface
    # points sampled from view 0's depth lands inside view 0.
    _, views = synth_views(cfg)
    v0 = scene.view("frame_0000.png")
    np.testing.assert_allclose(v0.R, views[0].view.R, atol=1e-9)
    np.testing.assert_allclose(v0.t, views[0].view.t, atol=1e-9)
    xc = scene.points @ v0.R.T + v0.t
    seen = xc[:, 2] > 0
    assert seen.mean() > 0.3
