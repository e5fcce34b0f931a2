"""The "photo" scene family (``pipeline.synth.photo``): layout, determinism, photo statistics, water
applied per supersample, true tracks, and a clear error without the photographs.

The albedo comes from the EUVP enhanced photographs (shared/data/textures/euvp-gtr-a), whose 8-bit values the
generator treats as J (scaled by ``albedo_scale`` and pulled towards their mean by ``contrast``): the
brightness/contrast bounds below depend on that definition, not on measured reflectance.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.records import ray_length_factor
from pipeline.synth.ground_truth import is_generated_scene, load_ground_truth
from pipeline.synth.photo import (
    PHOTO_WATER_PRESETS,
    PhotoSynthConfig,
    default_textures_dir,
    generate_photo_scene,
    make_camera,
    photo_views,
)
from pipeline.synth.photo_texture import TextureFolderError
from pipeline.synth.water import WATER_PRESETS

needs_photos = pytest.mark.skipif(not default_textures_dir().is_dir(),
                                  reason="shared/data/textures/euvp-gtr-a is not beside the repository")

# A 10 m terrain period instead of 20 m: a quarter of the world-building time, still wider than any footprint.
TINY = PhotoSynthConfig(views=12, width=64, height=48, preset="medium", seed=3, n_points=400, grid_size=512)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_photo_scene(TINY, tmp_path_factory.mktemp("photo"))


def _model(J: np.ndarray, z: np.ndarray, water: dict, ray: np.ndarray) -> np.ndarray:
    """The closed form applied per pixel to the pixel's mean J and depth.  # [H, W, 3]"""
    bd, bb, binf = (np.asarray(water[k], dtype=np.float64) for k in ("beta_D", "beta_B", "B_inf"))
    r = (z * ray)[..., None]
    return J * np.exp(-bd * r) + binf * (1 - np.exp(-bb * r))


@needs_photos
def test_layout_and_ground_truth(scene):
    from pipeline.scene.images import read_image

    names = [f"frame_{i:04d}.png" for i in range(TINY.views)]
    assert sorted(p.name for p in (scene / "images").glob("*.png")) == names
    assert sorted(p.name for p in (scene / "clean").glob("*.png")) == names
    assert {p.name for p in (scene / "sparse_gt").iterdir()} == {"cameras.txt", "images.txt", "points3D.txt"}
    assert read_image(scene / "images" / names[0]).shape == (48, 64, 3)
    for i in range(TINY.views):
        z = np.load(scene / "depth" / f"frame_{i:04d}.npy")
        assert z.dtype == np.float32 and z.shape == (48, 64)
        assert np.all(z > 0.5) and np.all(z < 999.0)  # every ray hits the (unbounded) seabed
    meta = json.loads((scene / "water.json").read_text())
    assert meta["family"] == "photo" and meta["preset"] == "medium" and meta["units"]["beta_D"] == "1/m"
    assert meta["beta_D"] == list(PHOTO_WATER_PRESETS["medium"].beta_D)
    assert meta["generator"]["views"] == 12 and meta["generator"]["albedo_scale"] == TINY.albedo_scale
    # Its own water, not the procedural family's.
    assert all(PHOTO_WATER_PRESETS[p] != WATER_PRESETS[p] for p in ("clear", "medium", "turbid"))
    assert is_generated_scene(scene)
    gt = load_ground_truth(scene)
    assert len(gt.scene.views) == 12 and gt.water["family"] == "photo"
    assert gt.clean(gt.scene.views[0]).shape == (48, 64, 3)


@needs_photos
def test_same_seed_same_bytes_other_seed_differs(scene, tmp_path):
    from pipeline.scene.images import read_image

    again = generate_photo_scene(TINY, tmp_path / "again")
    files = sorted(p.relative_to(scene) for p in scene.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (scene / rel).read_bytes() == (again / rel).read_bytes(), rel
    _, other = photo_views(replace(TINY, seed=4, views=2))
    same = [np.stack(x) for x in zip(*(
        (np.load(scene / "depth" / f"frame_{i:04d}.npy"), read_image(scene / "clean" / f"frame_{i:04d}.png"))
        for i in range(2)))]
    assert np.abs(other[0].J - same[1][0]).mean() > 0.02
    assert np.abs(other[1].depth - same[0][1]).mean() > 0.01


@needs_photos
def test_clean_radiance_is_dark_low_contrast_and_below_the_procedural_family():
    from pipeline.config import SynthConfig
    from pipeline.synth.procedural import synth_views

    _, photo = photo_views(replace(TINY, preset="none", views=6))
    _, proc = synth_views(SynthConfig(views=6, width=64, height=48, preset="none", seed=3, noise_std=0.0))
    J = np.stack([sv.J for sv in photo])  # [V, H, W, 3]
    Jp = np.stack([sv.J for sv in proc])
    # Enhanced photos average ≈ 0.4 per channel; × albedo_scale 0.6 × shading ≈ 0.9 gives ≈ 0.2.
    assert 0.12 < J.mean() < 0.30
    std = J.std(axis=(1, 2)).mean()  # per-view, per-channel contrast
    assert 0.04 < std < 0.12
    assert std < 0.8 * Jp.std(axis=(1, 2)).mean()
    assert J.mean() < Jp.mean()


@needs_photos
def test_written_pixels_follow_the_model_only_up_to_supersampling_and_noise(scene):
    from pipeline.scene.images import read_image

    meta = json.loads((scene / "water.json").read_text())
    ray = ray_length_factor(make_camera(TINY))
    err = []
    for i in range(TINY.views):
        name = f"frame_{i:04d}"
        I = read_image(scene / "images" / f"{name}.png")
        J = read_image(scene / "clean" / f"{name}.png")
        z = np.load(scene / "depth" / f"{name}.npy")
        err.append(np.abs(I - _model(J, z, meta, ray)).ravel())
    e = np.concatenate(err)
    # Noise std ≈ 0.006 at these intensities (median |n| ≈ 0.004) plus 8-bit rounding of I and J (≤ 1/255)
    # plus the per-supersample deviation at depth edges: measured mean 0.005, p99 0.016 at 64x48.
    assert e.mean() < 0.008
    assert np.quantile(e, 0.99) < 0.03


@needs_photos
def test_water_is_applied_per_supersample_not_per_pixel():
    cfg = replace(TINY, views=4, noise_gain=0.0, noise_floor=0.0)
    water = PHOTO_WATER_PRESETS[cfg.preset].to_json()
    ray = ray_length_factor(make_camera(cfg))
    _, views = photo_views(cfg)
    dev = np.concatenate([np.abs(sv.image - _model(sv.J, sv.depth, water, ray)).ravel() for sv in views])
    # Where J and depth are smooth inside a pixel the two agree; where they vary together inside a pixel
    # (boulder edges, grazing far field) mean(J·T(r)) ≠ mean(J)·T(mean r). With 2x2 supersamples the effect is
    # small — measured median 1e-5, max 1.6e-3 (≈ 0.4 DN) — but far above float error (the procedural family
    # matches its closed form to 1e-12).
    assert np.median(dev) < 1e-4
    assert dev.max() > 5e-4


@needs_photos
def test_turbid_water_has_less_contrast_than_clear():
    world, clear = photo_views(replace(TINY, preset="clear", views=3))
    _, turbid = photo_views(replace(TINY, preset="turbid", views=3), world)
    for c, t in zip(clear, turbid):
        np.testing.assert_array_equal(c.J, t.J)  # same seabed, only the water differs
        assert t.image.std(axis=(0, 1)).mean() < 0.7 * c.image.std(axis=(0, 1)).mean()
        assert c.image.std(axis=(0, 1)).mean() < c.J.std(axis=(0, 1)).mean()


@needs_photos
def test_true_tracks_project_onto_pixels_with_matching_depth(scene):
    from pipeline.scene.colmap import read_colmap

    model = read_colmap(scene / "sparse_gt", scene / "images")
    assert len(model.points) > 300 and model.sightings is not None
    n_obs, multi = 0, 0
    for view in model.views:
        seen = model.sightings[view.name]
        u, v, z = view.project(model.points[seen.point])
        np.testing.assert_allclose(np.stack([u, v], 1), seen.xy, atol=1e-3)
        depth = np.load(scene / "depth" / f"{Path(view.name).stem}.npy")
        ref = depth[np.floor(v).astype(int), np.floor(u).astype(int)]
        np.testing.assert_array_less(np.abs(z - ref), 0.02 * ref + 0.01)
        n_obs += len(seen.point)
    counts = np.bincount(np.concatenate([model.sightings[v.name].point for v in model.views]))
    multi = int((counts >= 2).sum())
    assert n_obs > 2 * len(model.points) and multi > 0.8 * len(model.points)  # real multi-view tracks


def test_missing_texture_folder_is_a_clear_error(tmp_path):
    with pytest.raises(TextureFolderError, match="seabed texture folder .*nowhere.* not found"):
        generate_photo_scene(replace(TINY, textures_dir=str(tmp_path / "nowhere")), tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing half-written


@needs_photos
def test_cli_synth_photo_family(tmp_path, capsys):
    from cli.main import main

    out = tmp_path / "cli"
    assert main(["synth", "--family", "photo", "--out", str(out), "--views", "4", "--size", "48x36",
                 "--preset", "turbid", "--seed", "2"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["family"] == "photo" and printed["preset"] == "turbid"
    meta = json.loads((out / "water.json").read_text())
    assert meta["generator"]["width"] == 48 and meta["generator"]["seed"] == 2 and is_generated_scene(out)


def test_march_hits_a_flat_grid_where_the_plane_is():
    import torch

    from pipeline.synth.photo_world import march, terrain_from_heights

    terrain = terrain_from_heights(torch.full((64, 64), 0.1, dtype=torch.float64), spacing=0.05)
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    d[:, 2] = -d[:, 2].abs() - 0.1  # downward, some grazing
    d = torch.nn.functional.normalize(d, dim=-1)
    o = torch.tensor([[0.3, -1.7, 2.5]], dtype=torch.float64).expand_as(d)
    t = march(terrain, o, d)
    torch.testing.assert_close(t, (2.5 - 0.1) / -d[:, 2], rtol=1e-6, atol=1e-6)
    assert torch.isinf(march(terrain, o[:1], torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))).all()


def test_march_matches_a_dense_brute_force_reference():
    """The coarse/fine/bisection marcher against the slow obvious reference: 1 mm steps along each ray."""
    import torch

    from pipeline.synth.photo_world import bilinear, make_terrain, march

    terrain = make_terrain(np.random.default_rng(0), n=256, spacing=0.02, relief_std=0.08, corr_length=2.0,
                           roughness_cut=0.06, boulders_per_m2=1.0, boulder_radius=(0.15, 0.4))
    g = torch.Generator().manual_seed(1)
    n = 200
    pitch = torch.rand(n, generator=g, dtype=torch.float64) * 1.2 + 0.3  # 17°–86° below the horizon
    yaw = torch.rand(n, generator=g, dtype=torch.float64) * 2 * np.pi
    d = torch.stack([pitch.cos() * yaw.cos(), pitch.cos() * yaw.sin(), -pitch.sin()], -1)
    o = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([5.0, 5.0, 1.0]) + torch.tensor(
        [0.0, 0.0, 1.5])
    t = march(terrain, o, d)
    steps = torch.arange(0, 12.0, 0.001, dtype=torch.float64)  # [S]
    ref = torch.empty(n, dtype=torch.float64)
    for i in range(n):
        p = o[i] + steps[:, None] * d[i]
        h = bilinear(terrain.height_q, terrain.size, terrain.spacing, p[:, 0], p[:, 1])
        ref[i] = steps[int(torch.nonzero(p[:, 2] <= h)[0])]
    # The reference is exact to its 1 mm step; the marcher may skip a crossing narrower than a fine step.
    close = (t - ref).abs() < 0.0011
    assert close.float().mean() > 0.97


@needs_photos
def test_cli_synth_a_survey_at_constant_range(tmp_path, capsys):
    """--altitude and --oblique: lawnmower lines at 2.4-2.6 m and no oblique pass, so every view sees the seabed
    from about the same distance (the narrow-range case of the water fit); they are the photo family's only."""
    from cli.main import main
    from pipeline.scene.colmap import read_colmap

    out = tmp_path / "narrow"
    assert main(["synth", "--family", "photo", "--out", str(out), "--views", "6", "--size", "48x36",
                 "--altitude", "2.4,2.6", "--oblique", "0"]) == 0
    gen = json.loads((out / "water.json").read_text())["generator"]
    assert gen["altitude_range"] == [2.4, 2.6] and gen["oblique_fraction"] == 0
    model = read_colmap(out / "sparse_gt", out / "images")
    heights = np.array([v.center[2] for v in model.views])
    assert heights.min() >= 2.4 - 0.031 and heights.max() <= 2.6 + 0.031  # the path's ±3 cm jitter
    assert main(["synth", "--out", str(tmp_path / "p"), "--altitude", "2,3"]) == 2
    with pytest.raises(SystemExit):
        main(["synth", "--family", "photo", "--out", str(tmp_path / "q"), "--oblique", "1.5"])


def test_cli_synth_a_camera_fall_off(tmp_path):
    """--fall-off: every photo darker towards its top and corners (linear light), recorded in fall_off.json; the
    field has mean 1 and spans 1.7x at 0.3 (AIMS Erub's survey mean image: 1.6x over its blocks)."""
    from cli.main import main
    from pipeline.scene.colour import srgb_to_linear
    from pipeline.scene.images import read_image
    from pipeline.synth.exposure import FALL_OFF_FILE, fall_off_field

    field = fall_off_field(320, 240, 0.3)
    assert field.mean() == pytest.approx(1.0) and field.max() / field.min() == pytest.approx(1.72, abs=0.02)
    plain, dark = tmp_path / "plain", tmp_path / "dark"
    for out, extra in ((plain, []), (dark, ["--fall-off", "0.3"])):
        assert main(["synth", "--family", "photo", "--out", str(out), "--views", "4", "--size", "64x48",
                     "--preset", "clear", *extra]) == 0
    assert json.loads((dark / FALL_OFF_FILE).read_text())["strength"] == 0.3 and not (plain / FALL_OFF_FILE).exists()
    ratio = []
    for p in sorted((plain / "images").iterdir()):
        a, b = (srgb_to_linear(read_image(d / "images" / p.name).astype(np.float64)) for d in (plain, dark))
        ratio.append((b[:12].mean() / a[:12].mean(), b[-12:].mean() / a[-12:].mean()))
    top, bottom = np.mean(ratio, axis=0)
    expect = fall_off_field(64, 48, 0.3)
    assert top == pytest.approx(expect[:12].mean(), rel=0.05) and bottom == pytest.approx(expect[-12:].mean(), rel=0.05)
    assert bottom > 1.2 * top
