"""Similarity alignment of camera centres and pose errors."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.scene.align import align_to_reference, rotation_angle_deg, umeyama
from pipeline.scene.records import Camera, Scene, View

CAM = Camera(8, 6, 5.0, 5.0, 4.0, 3.0)


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _ref_scene(n: int = 12) -> Scene:
    rng = np.random.default_rng(0)
    views = []
    for i in range(n):
        R = _rot(rng.normal(size=3), rng.uniform(0, 40))
        c = np.array([0.5 * i, np.sin(i), 2.0])
        views.append(View(f"{i:03d}.png", CAM, R, -R @ c))
    return Scene(views=views)


def _transformed(ref: Scene, s: float, A: np.ndarray, b: np.ndarray) -> Scene:
    """The same cameras in another frame: x_est = s A x_ref + b."""
    views = []
    for v in ref.views:
        R = v.R @ A.T
        c = s * A @ v.center + b
        views.append(View(v.name, CAM, R, -R @ c))
    return Scene(views=views)


def test_umeyama_recovers_similarity() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    A = _rot([1, 2, 3], 70)
    dst = 2.5 * src @ A.T + np.array([1.0, -2.0, 3.0])
    s, R, t = umeyama(src, dst)
    assert abs(s - 2.5) < 1e-12
    np.testing.assert_allclose(R, A, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-12)
    with pytest.raises(ValueError):
        umeyama(src[:2], dst[:2])


def test_alignment_of_exact_copy_gives_zero_error() -> None:
    ref = _ref_scene()
    est = _transformed(ref, 0.3, _rot([0, 1, 1], 120), np.array([5.0, 0.0, -1.0]))
    m = align_to_reference(est, ref)
    assert m["n_common"] == 12
    assert abs(m["scale"] - 1 / 0.3) < 1e-9
    assert m["rot_err_deg_max"] < 1e-6 and m["center_err_rel_max"] < 1e-9


def test_alignment_reports_perturbations() -> None:
    ref = _ref_scene()
    est = _transformed(ref, 1.0, np.eye(3), np.zeros(3))
    v = est.views[4]
    c = v.center
    v.R = _rot([0, 0, 1], 2.0) @ v.R
    v.t = -v.R @ c  # same centre, orientation off by 2°
    m = align_to_reference(est, ref)
    assert abs(m["rot_err_deg_max"] - 2.0) < 1e-6
    assert abs(m["rot_err_deg_mean"] - 2.0 / 12) < 1e-6
    assert m["center_err_max"] < 1e-9
    assert m["path_length"] > 5.5
    np.testing.assert_allclose(rotation_angle_deg(np.stack([np.eye(3), _rot([1, 0, 0], 90)])), [0, 90], atol=1e-6)


def test_alignment_needs_three_common_views() -> None:
    ref = _ref_scene(5)
    est = Scene(views=ref.views[:2])
    with pytest.raises(ValueError, match=">= 3"):
        align_to_reference(est, ref)
