"""COLMAP model IO: text / binary round trips, classic 3-file text, camera-model checks, quaternions."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.colmap import (
    ColmapModelError,
    UnsupportedCameraError,
    qvec_to_rotmat,
    read_colmap,
    read_reconstruction,
    rotmat_to_qvec,
    write_colmap_binary,
    write_colmap_text,
)
from pipeline.scene.records import Camera, Scene, View

RUIE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ruie-A188-A206"


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def make_scene(n_views: int = 5, n_points: int = 40, seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    cams = [Camera(64, 48, 55.5, 56.25, 32.1, 23.9), Camera(80, 60, 70.0, 70.0, 40.0, 30.0)]
    views = [
        View(f"v{i:03d}.png", cams[i % 2], random_rotation(rng), rng.normal(size=3)) for i in range(n_views)
    ]
    pts = rng.normal(size=(n_points, 3))
    cols = rng.integers(0, 256, size=(n_points, 3)) / 255.0
    return Scene(views=views, points=pts, colors=cols)


def assert_same_scene(a: Scene, b: Scene, atol: float = 1e-12) -> None:
    assert [v.name for v in a.views] == [v.name for v in b.views]
    for va, vb in zip(a.views, b.views, strict=True):
        assert va.camera == vb.camera
        np.testing.assert_allclose(va.R, vb.R, atol=atol)
        np.testing.assert_allclose(va.t, vb.t, atol=atol)
    order_a, order_b = np.lexsort(a.points.T), np.lexsort(b.points.T)
    np.testing.assert_allclose(a.points[order_a], b.points[order_b], atol=atol)
    np.testing.assert_allclose(a.colors[order_a], b.colors[order_b], atol=1e-9)


def test_text_round_trip(tmp_path: Path) -> None:
    s = make_scene()
    write_colmap_text(s, tmp_path / "m")
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    back = read_colmap(tmp_path / "m", images_dir=tmp_path / "imgs")
    assert_same_scene(s, back)
    assert back.views[2].image_path == tmp_path / "imgs" / "v002.png"
    assert len(read_reconstruction(tmp_path / "m").cameras) == 2  # identical cameras shared


def test_binary_round_trip(tmp_path: Path) -> None:
    s = make_scene(seed=1)
    write_colmap_binary(s, tmp_path / "b")
    names = sorted(p.name for p in (tmp_path / "b").iterdir())
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= set(names)
    assert not any(n.endswith(".txt") for n in names)
    assert_same_scene(s, read_colmap(tmp_path / "b"))


def test_simple_pinhole_is_accepted(tmp_path: Path) -> None:
    m = tmp_path / "m"
    m.mkdir()
    (m / "cameras.txt").write_text("1 SIMPLE_PINHOLE 64 48 50 32 24\n")
    (m / "images.txt").write_text("1 1 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 1 0 3 1 b.png\n\n")
    (m / "points3D.txt").write_text("1 0 0 5 255 0 0 0.5\n")
    s = read_colmap(m)
    assert s.views[0].camera == Camera(64, 48, 50.0, 50.0, 32.0, 24.0)
    np.testing.assert_allclose(s.views[1].center, [-1.0, 0.0, -3.0])
    np.testing.assert_allclose(s.colors, [[1.0, 0.0, 0.0]])


def test_classic_three_file_text_model_loads(tmp_path: Path) -> None:
    """pycolmap 4 writes rigs/frames too; the COLMAP 3 layout without them must still load."""
    for n in ("cameras", "images", "points3D"):
        shutil.copy(RUIE / "sparse_ref" / f"{n}.txt", tmp_path / f"{n}.txt")
    rec = read_reconstruction(tmp_path)
    assert rec.num_reg_images() == 19 and rec.num_points3D() == 1871
    assert abs(rec.compute_mean_reprojection_error() - 1.11) < 0.01  # shared/data/real README: 1.11 px


def test_distorted_camera_is_a_typed_error() -> None:
    with pytest.raises(UnsupportedCameraError, match="SIMPLE_RADIAL") as ei:
        read_colmap(RUIE / "sparse_ref")
    assert ei.value.models == ["SIMPLE_RADIAL"] and "undistort" in str(ei.value).lower()


def test_missing_or_broken_model(tmp_path: Path) -> None:
    with pytest.raises(ColmapModelError, match="no COLMAP model"):
        read_colmap(tmp_path)
    for n in ("cameras", "images", "points3D"):
        (tmp_path / f"{n}.bin").write_bytes(b"\x07" * 5)
    with pytest.raises(ColmapModelError, match="cannot parse"):
        read_colmap(tmp_path)


def test_quaternion_conversions() -> None:
    rng = np.random.default_rng(0)
    rots = [random_rotation(rng) for _ in range(50)]
    rots += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]  # 180° and identity
    for R in rots:
        q = rotmat_to_qvec(R)
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
        np.testing.assert_allclose(qvec_to_rotmat(q), R, atol=1e-12)
    # COLMAP convention (w, x, y, z): 90° about z.
    np.testing.assert_allclose(rotmat_to_qvec(qvec_to_rotmat([1, 0, 0, 1])), [2**-0.5, 0, 0, 2**-0.5], atol=1e-12)
