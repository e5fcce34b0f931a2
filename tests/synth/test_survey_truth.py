"""The true seabed on a grid (``pipeline.synth.survey_truth``): pixels of a generated scene back-projected with their
true depth land where true_surface puts the seabed, in the colour clean/ holds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.colmap import read_colmap
from pipeline.scene.images import read_image
from pipeline.synth.photo import PhotoSynthConfig, default_textures_dir, generate_photo_scene
from pipeline.synth.survey_truth import load_surface_truth, scene_config, true_surface

needs_photos = pytest.mark.skipif(not default_textures_dir().is_dir(),
                                  reason="shared/data/textures/euvp-gtr-a is not beside the repository")

# supersample 1: each clean/ pixel and depth value is the one ray through the pixel centre, so a back-projected
# pixel is the very surface point whose colour it holds (with 2x2 supersamples it would be a 4-point average).
CFG = PhotoSynthConfig(views=6, width=160, height=120, seed=7, grid_size=512, n_points=100, supersample=1,
                       gps_origin=(-9.5988, 143.7811))
MARGIN = 10  # pixels kept away from the frame's edges


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_photo_scene(CFG, tmp_path_factory.mktemp("truth"))


def _back_projected(scene: Path, rng: np.random.Generator, per_view: int = 200):
    """Random interior pixels of every view → (world points [N, 3], their clean/ colours [N, 3])."""
    pts, cols = [], []
    for v in read_colmap(scene / "sparse_gt", scene / "images").views:
        cam, stem = v.camera, Path(v.name).stem
        depth, clean = np.load(scene / "depth" / f"{stem}.npy"), read_image(scene / "clean" / v.name)
        u = rng.integers(MARGIN, cam.width - MARGIN, per_view)
        w = rng.integers(MARGIN, cam.height - MARGIN, per_view)
        z = depth[w, u].astype(np.float64)
        xc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (w + 0.5 - cam.cy) / cam.fy * z, z], 1)
        pts.append((xc - v.t) @ v.R)  # X = R^T (x_cam − t)
        cols.append(clean[w, u].astype(np.float64))
    return np.concatenate(pts), np.concatenate(cols)


@needs_photos
def test_true_surface_matches_back_projected_clean_pixels(scene):
    pts, cols = _back_projected(scene, np.random.default_rng(0))
    height, colour = true_surface(scene, pts[:, 0], pts[:, 1])
    assert height.shape == (len(pts),) and colour.shape == (len(pts), 3)
    # Depth is stored as float32 (≈ 0.2 µm at 3 m) and the marcher's crossing is refined to micrometres.
    np.testing.assert_allclose(height, pts[:, 2], atol=1e-4)  # seen: 5 µm
    # clean/ holds the colour rounded to 8 bits (±0.5/255, seen: 0.4999/255); 1/255 leaves room for float32
    # texture sampling. One centimetre off, the errors are 27 mm and 48/255.
    err = np.abs(colour - cols)
    assert err.max() < 1.0 / 255, f"worst colour error {err.max() * 255:.2f}/255"
    assert np.ptp(cols, axis=0).min() > 0.1  # a textured seabed, not a flat colour that would match anywhere


@needs_photos
def test_any_shape_and_cell_means(scene):
    truth = load_surface_truth(scene)
    x, y = np.meshgrid(np.linspace(-1.0, 1.0, 5), np.linspace(-0.5, 0.5, 3))  # [3, 5]
    h, c = truth.at(x, y)
    assert h.shape == (3, 5) and c.shape == (3, 5, 3) and np.all((c >= 0) & (c <= 1))
    h1, c1 = truth.at(x, y, cell=0.05, samples=1)  # one sample: the cell centre
    np.testing.assert_array_equal(h1, h)
    np.testing.assert_array_equal(c1, c)
    cell, k = 0.05, 3
    off = (np.arange(k) - 1) * cell / k  # sub-sample centres of a 3x3 split of the cell
    hs, cs = zip(*(truth.at(x + dx, y + dy) for dx in off for dy in off))
    h3, c3 = truth.at(x, y, cell=cell, samples=k)
    np.testing.assert_allclose(h3, np.mean(hs, 0), atol=1e-12)
    np.testing.assert_allclose(c3, np.mean(cs, 0), atol=1e-12)  # an "srgb" scene averages encoded colours
    with pytest.raises(ValueError, match="equal shapes"):
        truth.at(x, y[:1])


@needs_photos
def test_scene_config_round_trips_and_refuses_other_families(scene, tmp_path):
    assert scene_config(scene) == CFG
    (tmp_path / "water.json").write_text(json.dumps({"family": "procedural", "generator": {}}))
    with pytest.raises(ValueError, match="not a generated photo-family scene"):
        scene_config(tmp_path)
