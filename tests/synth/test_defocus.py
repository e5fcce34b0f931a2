"""A lens's sharpness falling with distance (pipeline.synth.defocus): sharp at the focus, blurred beyond it,
colour kept."""

from __future__ import annotations

import numpy as np

from pipeline.synth.defocus import defocus


def test_sharp_at_the_focus_blurred_far_behind_it_and_the_mean_kept():
    h, w = 40, 80
    img = np.zeros((h, w, 3), np.float32)
    img[:, ::4] = 1.0  # fine vertical stripes
    depth = np.full((h, w), 2.0, np.float32)
    depth[:, w // 2:] = 20.0  # the right half far behind the focus
    out = defocus(img, depth, focus=2.0, blur_at_infinity=8.0)
    left, right = out[:, 8:w // 2 - 8], out[:, w // 2 + 8:-8]
    np.testing.assert_allclose(left, img[:, 8:w // 2 - 8], atol=1e-6)  # in focus: untouched
    assert right.std() < 0.05 * img.std()  # σ ≈ 3.6 px wipes out 4-px stripes
    assert abs(right.mean() - img.mean()) < 0.01  # blur moves no colour
    open_water = np.full((h, w), np.inf, np.float32)  # nothing hit: blurred as at infinity, no NaN
    assert np.isfinite(defocus(img, open_water, 2.0, 8.0)).all()
    np.testing.assert_array_equal(defocus(img, depth, 2.0, 0.0), img)
