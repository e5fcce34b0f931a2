"""Image IO: round trips per bit depth, EXIF orientation, content-based format detection, clear errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.images import (
    ImageReadError,
    list_images,
    read_image,
    read_pixels,
    resize_area,
    resize_area_to,
    write_image,
)
from pipeline.scene.records import Camera

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


def _rgb(h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((h, w, 3), dtype=np.float32)


def test_png_8bit_round_trip_is_exact_after_quantisation(tmp_path: Path) -> None:
    a = _rgb()
    write_image(tmp_path / "a.png", a)
    b = read_image(tmp_path / "a.png")
    assert b.shape == (24, 32, 3) and b.dtype == np.float32
    np.testing.assert_allclose(b, np.rint(a * 255) / 255, atol=1e-6)


def test_uint8_array_round_trip_exact(tmp_path: Path) -> None:
    a = (np.arange(24 * 32 * 3) % 256).astype(np.uint8).reshape(24, 32, 3)
    write_image(tmp_path / "u.png", a)
    np.testing.assert_array_equal(np.rint(read_image(tmp_path / "u.png") * 255).astype(np.uint8), a)


def test_png_16bit_keeps_16bit_precision(tmp_path: Path) -> None:
    a = _rgb()
    write_image(tmp_path / "a16.png", a, bits=16)
    b = read_image(tmp_path / "a16.png")
    err = np.abs(b - a).max()
    assert err <= 0.5 / 65535 + 1e-7  # 8-bit storage would give up to 0.5/255 ≈ 2e-3
    u16 = (a * 65535).astype(np.uint16)
    write_image(tmp_path / "u16.png", u16)
    np.testing.assert_array_equal(np.rint(read_image(tmp_path / "u16.png") * 65535).astype(np.uint16), u16)


@pytest.mark.parametrize("ext", [".exr", ".tif"])
def test_float_formats_round_trip_exactly(tmp_path: Path, ext: str) -> None:
    a = _rgb()
    write_image(tmp_path / f"f{ext}", a)
    np.testing.assert_array_equal(read_image(tmp_path / f"f{ext}"), a)


def test_float_exr_keeps_values_above_one_in_read_pixels(tmp_path: Path) -> None:
    d = np.array([[0.5, 3.0], [1e3, 0.0]], dtype=np.float32)  # e.g. a depth map
    write_image(tmp_path / "d.exr", d)
    px = read_pixels(tmp_path / "d.exr")
    assert px.shape == (2, 2, 1)
    np.testing.assert_array_equal(px[..., 0], d)
    assert read_image(tmp_path / "d.exr").max() == 1.0  # read_image clips photos to [0, 1]


def test_jpeg_is_lossy_but_close(tmp_path: Path) -> None:
    a = np.clip(resize_area(_rgb(96, 128), 0.25) * 0.5 + 0.25, 0, 1)  # smooth-ish content
    write_image(tmp_path / "a.jpg", a, quality=95)
    b = read_image(tmp_path / "a.jpg")
    assert b.shape == a.shape
    assert np.abs(b - a).mean() < 0.03


def test_grey_is_replicated_and_alpha_dropped(tmp_path: Path) -> None:
    g = np.linspace(0, 1, 12 * 16, dtype=np.float32).reshape(12, 16)
    write_image(tmp_path / "g.png", g)
    img = read_image(tmp_path / "g.png")
    assert img.shape == (12, 16, 3)
    np.testing.assert_array_equal(img[..., 0], img[..., 2])
    np.testing.assert_allclose(img[..., 1], np.rint(g * 255) / 255, atol=1e-6)
    rgba = np.concatenate([_rgb(12, 16), np.zeros((12, 16, 1), np.float32)], axis=2)
    write_image(tmp_path / "rgba.png", rgba)
    img = read_image(tmp_path / "rgba.png")
    assert img.shape == (12, 16, 3)
    np.testing.assert_allclose(img, np.rint(rgba[..., :3] * 255) / 255, atol=1e-6)


def _write_with_orientation(path: Path, a: np.ndarray, orientation: int) -> None:
    import OpenImageIO as oiio

    h, w, c = a.shape
    spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image((a * 255).round().astype(np.uint8))
    out.close()


def test_exif_orientation_6_rotates_jpeg_and_tiff(tmp_path: Path) -> None:
    a = np.rint(_rgb(40, 60) * 255) / 255
    _write_with_orientation(tmp_path / "o6.jpg", a, 6)
    _write_with_orientation(tmp_path / "o6.tif", a, 6)
    assert read_image(tmp_path / "o6.jpg").shape == (60, 40, 3)  # stored 60 wide, displayed 60 tall
    # Lossless TIFF: orientation 6 means "rotate 90° clockwise to display".
    np.testing.assert_allclose(read_image(tmp_path / "o6.tif"), np.rot90(a, k=-1), atol=1e-6)


def test_misnamed_jpeg_reads_by_content() -> None:
    p = REAL / "u45" / "blue" / "29.png"
    assert p.read_bytes()[:3] == b"\xff\xd8\xff"  # really a JPEG
    img = read_image(p)
    assert img.shape == (256, 256, 3)
    assert 0.05 < float(img.mean()) < 0.95


def test_errors_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "garbage.jpg").write_bytes(np.random.default_rng(0).bytes(3000))
    (tmp_path / "notes.png").write_text("not an image")
    for name in ("garbage.jpg", "notes.png", "missing.png"):
        with pytest.raises(ImageReadError) as ei:
            read_image(tmp_path / name)
        assert name in str(ei.value) and ei.value.path == tmp_path / name and ei.value.reason


def test_truncated_jpeg_is_an_error_not_grey_pixels(tmp_path: Path) -> None:
    src = REAL / "ruie-A188-A206" / "images" / "A_190.jpg"
    (tmp_path / "cut.jpg").write_bytes(src.read_bytes()[:20000])
    with pytest.raises(ImageReadError, match="cut.jpg"):
        read_image(tmp_path / "cut.jpg")


def test_list_images_filters_and_sorts(tmp_path: Path) -> None:
    for n in ("b.JPG", "a.png", "c.Tiff", "d.txt", ".hidden.jpg", "._a.png", "e.jpeg", "f.exr"):
        (tmp_path / n).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "g.jpg").write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == ["a.png", "b.JPG", "c.Tiff", "e.jpeg", "f.exr"]
    with pytest.raises(FileNotFoundError):
        list_images(tmp_path / "nope")


@pytest.mark.parametrize("factor", [1.0, 0.5, 0.37, 0.25, 0.1])
def test_resize_area_sizes_match_scaled_camera_and_mean_is_kept(factor: float) -> None:
    img = _rgb(61, 83, seed=3)
    out = resize_area(img, factor)
    cam = Camera(83, 61, 50.0, 50.0, 41.5, 30.5).scaled(factor)
    assert out.shape == (cam.height, cam.width, 3)
    np.testing.assert_allclose(out.mean(axis=(0, 1)), img.mean(axis=(0, 1)), atol=1e-5)


def test_resize_area_averages_blocks_and_antialiases() -> None:
    img = _rgb(8, 12, seed=1)
    out = resize_area(img, 0.5)
    np.testing.assert_allclose(out, img.reshape(4, 2, 6, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    checker = (np.indices((64, 64)).sum(0) % 2).astype(np.float32)
    small = resize_area_to(checker, (21, 21))  # non-integer factor
    assert np.abs(small - 0.5).max() < 0.05  # a point sampler would alias to 0/1
    with pytest.raises(ValueError):
        resize_area_to(checker, (65, 64))


def test_write_image_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="shape"):
        write_image(tmp_path / "x.png", np.zeros((4, 4, 2)))
    with pytest.raises(ValueError, match="16"):
        write_image(tmp_path / "x.jpg", np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ValueError, match="extension"):
        write_image(tmp_path / "x.gif", np.zeros((4, 4, 3)))
    assert not any(tmp_path.iterdir())


def test_write_is_atomic_and_overwrites(tmp_path: Path) -> None:
    write_image(tmp_path / "a.png", np.zeros((4, 4, 3)))
    write_image(tmp_path / "a.png", np.ones((4, 4, 3)))
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]
    assert read_image(tmp_path / "a.png").min() == 1.0
    shutil.rmtree(tmp_path)
