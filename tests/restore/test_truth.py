"""The full-resolution scoring's own measures: the edge offset recovers a known sub-pixel shift, and a render
carried into a photo's geometry lands where the lens puts it."""

import numpy as np
import pytest

from pipeline.restore.truth import edge_offset, warp_to_photo
from pipeline.scene.records import Camera, LensCamera


def _smooth_noise(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    k /= k.sum()
    img = rng.random((h, w))
    img = np.apply_along_axis(lambda c: np.convolve(c, k, "same"), 0, img)
    return np.apply_along_axis(lambda r: np.convolve(r, k, "same"), 1, img)


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    fy, fx = np.fft.fftfreq(img.shape[0])[:, None], np.fft.fftfreq(img.shape[1])[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * dx + fy * dy))))


@pytest.mark.parametrize("dx,dy", [(0.0, 0.0), (0.3, 0.0), (1.25, -0.5), (-3.7, 2.2)])
def test_edge_offset_recovers_a_known_shift(dx, dy):
    img = _smooth_noise(240, 320)
    assert abs(edge_offset(_shifted(img, dx, dy), img) - np.hypot(dx, dy)) < 0.05


def test_warp_to_photo_is_the_identity_for_a_pinhole_photo_of_the_render_size():
    cam = Camera(64, 48, 60.0, 60.0, 32.0, 24.0)
    img = np.random.default_rng(1).random((48, 64, 3)).astype(np.float32)
    lens = LensCamera("PINHOLE", 64, 48, (60.0, 60.0, 32.0, 24.0))
    assert np.abs(warp_to_photo(img, cam, lens) - img).max() < 1e-5


def test_warp_to_photo_follows_the_lens():
    """A radially distorted photo of a render: the render's pixel under each photo pixel is where the undistorted
    ray lands; a bright dot in the render appears at the distorted position."""
    cam = Camera(160, 120, 150.0, 150.0, 80.0, 60.0)
    img = np.zeros((120, 160, 1), np.float32)
    img[20, 130] = 1.0  # a dot near the corner (pixel centre 130.5, 20.5)
    lens = LensCamera("SIMPLE_RADIAL", 160, 120, (150.0, 80.0, 60.0, -0.2))
    out = warp_to_photo(img, cam, lens)[..., 0]
    y, x = np.unravel_index(int(np.argmax(out)), out.shape)
    xn, yn = (130.5 - 80) / 150, (20.5 - 60) / 150
    d = 1 - 0.2 * (xn * xn + yn * yn)  # SIMPLE_RADIAL: distorted = undistorted * (1 + k r²)
    assert abs(x + 0.5 - (150 * xn * d + 80)) <= 1.0 and abs(y + 0.5 - (150 * yn * d + 60)) <= 1.0
