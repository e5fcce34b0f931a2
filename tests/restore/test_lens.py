"""The lens map: the interpolated grid against the exact per-pixel undistortion."""

import numpy as np

from pipeline.restore.lens import LensGrid, exact_rays, render_position
from pipeline.scene.records import Camera, LensCamera


def test_grid_matches_exact_map_to_a_hundredth_of_a_pixel():
    W, H = 1600, 1200
    lens = LensCamera("SIMPLE_RADIAL", W, H, (float(W), W / 2, H / 2, -0.2))
    grid = LensGrid(lens)
    assert grid.error < 0.005 and grid.step == 4  # step 8 errs 0.0108 px here (measured)
    for y0, y1 in ((0, 40), (580, 620), (1160, 1200)):
        xn, yn = grid.rays(y0, y1)
        ex, ey = exact_rays(lens, y0, y1)
        assert max(np.abs(xn - ex).max(), np.abs(yn - ey).max()) * W < 0.006


def test_opencv_model_and_pinhole_identity():
    lens = LensCamera("OPENCV", 320, 240, (300.0, 310.0, 161.0, 119.0, -0.15, 0.05, 0.001, -0.002))
    xn, yn = LensGrid(lens).rays(0, 240)
    ex, ey = exact_rays(lens, 0, 240)
    assert max(np.abs(xn - ex).max(), np.abs(yn - ey).max()) * 300 < 0.006
    pin = LensCamera("PINHOLE", 320, 240, (300.0, 300.0, 160.0, 120.0))
    xn, yn = LensGrid(pin).rays(0, 240)
    u, v = render_position(xn, yn, Camera(320, 240, 300.0, 300.0, 160.0, 120.0))
    assert np.abs(u - (np.arange(320) + 0.5)).max() < 1e-4  # pixel-centre convention end to end
    assert np.abs(v - (np.arange(240) + 0.5)[:, None]).max() < 1e-4


def test_photo_view_pads_the_render_camera_to_the_photos_edges():
    """A barrel lens's photo reaches beyond the undistorted crop: the padded camera holds every photo pixel's ray,
    with no more than one pixel to spare beyond the bilinear neighbour; a photo inside the crop pads nothing."""
    from pipeline.restore.synthetic import SynthFrame
    from pipeline.restore.views import photo_view
    from pipeline.scene.records import View

    fr = SynthFrame(640, 480, factor=8, k1=-0.1)
    view = View("x.png", fr.render_camera, np.eye(3), np.zeros(3))
    padded, pad = photo_view(view, fr.lens)
    c = padded.camera
    assert pad >= 2 and (c.width, c.height) == (80 + 2 * pad, 60 + 2 * pad) and c.fx == view.camera.fx
    xn, yn = exact_rays(fr.lens, 0, 480)
    u, v = c.fx * xn + c.cx, c.fy * yn + c.cy
    assert u.min() >= 0 and v.min() >= 0 and u.max() <= c.width and v.max() <= c.height
    inner = min(u.min(), v.min(), c.width - u.max(), c.height - v.max())
    assert inner <= 2.0, inner  # the pad is the overshoot rounded up, plus one pixel
    u0 = view.camera.fx * xn + view.camera.cx
    assert u0.min() < 0  # without the pad the photo's edge lands outside the render
    plain = LensCamera("PINHOLE", 80, 60, (fr.render_camera.fx, fr.render_camera.fy, 40.0, 30.0))
    assert photo_view(view, plain) == (view, 0)
    from pipeline.restore.guided import default_radius  # the filter's radius follows the unpadded render

    assert default_radius(fr.lens, c, pad) == default_radius(fr.lens, view.camera) == 4
