"""Scene folder layouts: 3DGS/COLMAP, SeaThru-NeRF (distorted → undistorted cache), generator, errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.colmap import write_colmap_binary, write_colmap_text
from pipeline.scene.images import write_image
from pipeline.scene.loader import (
    ImageSizeError,
    SceneLayoutError,
    find_layout,
    load_images,
    load_scene,
    load_view_image,
)
from pipeline.scene.records import Camera, Scene, View

RUIE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ruie-A188-A206"


def _tiny_scene(root: Path, *, sparse: str = "sparse/0", binary: bool = False, n: int = 4) -> Scene:
    """A posed 64x48 scene written in a layout (images/ + ``sparse``)."""
    cam = Camera(64, 48, 60.0, 60.0, 32.0, 24.0)
    rng = np.random.default_rng(0)
    views = [View(f"im{i}.png", cam, np.eye(3), np.array([0.1 * i, 0.0, 2.0])) for i in range(n)]
    for v in views:
        write_image(root / "images" / v.name, rng.random((48, 64, 3), dtype=np.float32))
    s = Scene(views=views, points=rng.normal(size=(10, 3)), colors=rng.random((10, 3)))
    (write_colmap_binary if binary else write_colmap_text)(s, root / sparse)
    return s


@pytest.mark.parametrize(("sparse", "binary"), [("sparse/0", False), ("sparse/0", True), ("sparse_gt", False)])
def test_pinhole_layouts_load_directly(tmp_path: Path, sparse: str, binary: bool) -> None:
    _tiny_scene(tmp_path, sparse=sparse, binary=binary)
    s = load_scene(tmp_path, workdir=tmp_path / "wd")
    assert len(s.views) == 4 and s.root == tmp_path and len(s.points) == 10
    assert s.views[1].image_path == tmp_path / "images" / "im1.png"
    assert s.views[0].camera == Camera(64, 48, 60.0, 60.0, 32.0, 24.0)
    assert not (tmp_path / "wd").exists()  # nothing to undistort


def test_downscale_scales_cameras_and_images(tmp_path: Path) -> None:
    _tiny_scene(tmp_path)
    s = load_scene(tmp_path, downscale=2)
    cam = s.views[0].camera
    assert (cam.width, cam.height, cam.fx, cam.cx) == (32, 24, 30.0, 16.0)
    imgs = load_images(s)
    assert len(imgs) == 4 and all(im.shape == (24, 32, 3) for im in imgs)
    with pytest.raises(ValueError):
        load_scene(tmp_path, downscale=0.5)


def test_image_smaller_than_camera_is_an_error(tmp_path: Path) -> None:
    _tiny_scene(tmp_path)
    write_image(tmp_path / "images" / "im2.png", np.zeros((20, 30, 3)))
    s = load_scene(tmp_path)
    with pytest.raises(ImageSizeError, match="im2.png"):
        load_view_image(s.views[2])


def test_missing_pieces_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(SceneLayoutError, match="does not exist"):
        load_scene(tmp_path / "nope")
    (tmp_path / "images").mkdir()
    with pytest.raises(SceneLayoutError, match="COLMAP model") as ei:
        load_scene(tmp_path)
    assert "image folder" not in str(ei.value)
    _tiny_scene(tmp_path)
    (tmp_path / "images" / "im3.png").unlink()
    with pytest.raises(SceneLayoutError, match="1 of 4 images .* missing .*im3.png"):
        load_scene(tmp_path)


def _seathru_like(root: Path) -> None:
    """RUIE frames in a SeaThru-NeRF layout: Images_wb/ + sparse/0 with an OPENCV camera (text)."""
    shutil.copytree(RUIE / "images", root / "Images_wb")
    (root / "sparse" / "0").mkdir(parents=True)
    for n in ("images", "points3D"):
        shutil.copy(RUIE / "sparse_ref" / f"{n}.txt", root / "sparse" / "0" / f"{n}.txt")
    # SIMPLE_RADIAL f, cx, cy, k  ->  OPENCV fx, fy, cx, cy, k1, k2, p1, p2 (same distortion).
    line = [ln for ln in (RUIE / "sparse_ref" / "cameras.txt").read_text().splitlines() if ln[:1].isdigit()][0]
    cid, _, w, h, f, cx, cy, k = line.split()
    (root / "sparse" / "0" / "cameras.txt").write_text(f"{cid} OPENCV {w} {h} {f} {f} {cx} {cy} {k} 0 0 0\n")


def test_seathru_layout_is_undistorted_into_a_reused_cache(tmp_path: Path) -> None:
    root = tmp_path / "scene"
    _seathru_like(root)
    assert find_layout(root) == (root / "Images_wb", root / "sparse" / "0")
    wd = tmp_path / "wd"
    s = load_scene(root, workdir=wd)
    assert len(s.views) == 19 and len(s.points) == 1871
    cam = s.views[0].camera
    assert cam.width < 400 and cam.height < 300 and abs(cam.fx - 293.64) < 0.01  # PINHOLE, cropped
    assert all(v.image_path is not None and v.image_path.parent == wd / "images" for v in s.views)
    assert load_view_image(s.views[0]).shape == (cam.height, cam.width, 3)
    stamp = (wd / "sparse" / "cameras.bin").stat().st_mtime_ns
    s2 = load_scene(root, workdir=wd, downscale=2)
    assert (wd / "sparse" / "cameras.bin").stat().st_mtime_ns == stamp  # cache reused
    assert s2.views[0].camera.width == round(cam.width / 2)


def test_ruie_reference_model_goes_through_undistortion(tmp_path: Path) -> None:
    s = load_scene(RUIE, workdir=tmp_path / "wd")  # images/ + sparse_ref/ (SIMPLE_RADIAL)
    assert len(s.views) == 19 and s.root == RUIE
    assert {v.camera for v in s.views} == {s.views[0].camera}  # one shared PINHOLE camera
    assert not (RUIE / "_undistorted").exists()


def test_undistortion_never_wipes_a_foreign_folder(tmp_path: Path) -> None:
    wd = tmp_path / "mine"
    wd.mkdir()
    (wd / "precious.txt").write_text("keep")
    with pytest.raises(SceneLayoutError, match="not a dualphys cache"):
        load_scene(RUIE, workdir=wd)
    assert (wd / "precious.txt").read_text() == "keep"
