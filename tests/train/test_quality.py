"""Does the model keep its scene: coverage, point coverage, water share, collapse verdicts (pipeline.train.quality)."""

from __future__ import annotations

import numpy as np

from pipeline.scene.records import Camera, Scene, Sightings, View
from pipeline.scene.seen import view_points
from pipeline.train.quality import (
    collapse_warnings,
    lost_view,
    opacity_histogram,
    view_quality,
)


def test_view_quality_counts_covered_pixels_and_points():
    alpha = np.zeros((10, 20))
    alpha[:, :10] = 0.9  # left half covered
    pts = np.array([[2.5, 3.5], [5.5, 9.5], [15.5, 1.5], [19.9, 9.9]])  # 2 left, 2 right
    q = view_quality("v", alpha, pts)
    assert q.coverage == 0.5 and q.point_coverage == 0.5 and q.n_points == 4 and q.water_share is None
    water = np.full((10, 20, 3), 0.1)
    pred = np.full((10, 20, 3), 0.4)
    assert abs(view_quality("v", alpha, pts, water, pred).water_share - 0.25) < 1e-9
    assert view_quality("v", alpha, np.zeros((0, 2))).point_coverage is None


def test_collapse_is_most_views_lost_or_a_tiny_model():
    photo = np.full((4, 4, 3), 0.3)
    ok = view_quality("a", np.ones((4, 4)), np.array([[1.0, 1.0]]), photo=photo)
    lost = view_quality("b", np.zeros((4, 4)), np.array([[1.0, 1.0]]), photo=photo)
    assert lost.uncovered_content == 1.0 and lost_view(lost) and not lost_view(ok)
    assert collapse_warnings([ok, ok], 5000, 10_000) == (False, [])
    collapsed, warnings = collapse_warnings([ok, lost, lost], 5000, 10_000)
    assert collapsed and "2 of 3 training views lost their scene" in warnings[0] and "b" in warnings[0]
    # one view of open water (or one lost view) among held ones is a warning, never a failed job
    collapsed, warnings = collapse_warnings([ok, ok, lost], 5000, 10_000)
    assert not collapsed and "mostly uncovered" in warnings[0]
    collapsed, warnings = collapse_warnings([ok, ok], 168, 100_000)  # the reported 168-Gaussian model
    assert collapsed and "168 Gaussians" in warnings[0]
    # a black frame left uncovered shows nothing: not lost
    black = view_quality("k", np.zeros((4, 4)), np.zeros((0, 2)), photo=np.zeros((4, 4, 3)))
    assert black.uncovered_content == 0.0 and collapse_warnings([black, black], 5000, 10_000) == (False, [])


def test_sparse_points_on_uncovered_pixels_are_a_warning_and_none_in_plain_splatting():
    """A healthy plain 3DGS model of a generated scene without water left 45-50 % of every view's feature points
    under alpha 0.5 (dark pebbles over the black background): the job must not fail on it, nor warn."""
    alpha = np.ones((10, 10))
    alpha[:, :5] = 0.2  # the dark half drawn faint
    pts = np.array([[2.5, 5.5]] * 55 + [[7.5, 5.5]] * 45)
    q = view_quality("dark", alpha, pts, photo=np.full((10, 10, 3), 0.02))
    assert abs(q.point_coverage - 0.45) < 1e-9 and not lost_view(q)
    assert collapse_warnings([q] * 21, 80_000, 100_000, medium=False) == (False, [])
    collapsed, warnings = collapse_warnings([q] * 21, 80_000, 100_000, medium=True)
    assert not collapsed and "sparse points uncovered" in warnings[0] and "worst dark 45% covered" in warnings[0]


def test_view_points_prefers_tracks_and_rescales_them():
    cam = Camera(40, 30, 30.0, 30.0, 20.0, 15.0)
    v = View("a.png", cam, np.eye(3), np.zeros(3))
    pts = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.0, -1.0]])
    scene = Scene([v], pts)
    xy = view_points(scene, v)  # no tracks: projections inside the frame and in front
    np.testing.assert_allclose(xy, [[20.0, 15.0], [27.5, 15.0]])
    scene.sightings = {"a.png": Sightings(np.array([1]), np.array([[55.0, 30.0]]), width=80)}
    np.testing.assert_allclose(view_points(scene, v), [[27.5, 15.0]])  # the track, at half the model's size


def test_opacity_histogram_bins_everything():
    h = opacity_histogram(np.array([0.001, 0.007, 0.3, 0.95, 1.0]))
    assert sum(h.values()) == 5 and h["0-0.005"] == 1 and h["0.9-1"] == 2


def test_point_depth_tells_a_surface_drawn_far_behind_the_points():
    alpha = np.ones((10, 10))
    pts = np.array([[1.5, 1.5], [5.5, 5.5], [8.5, 2.5], [2.5, 8.5]])
    near = np.full((10, 10), 4.0)
    far = near.copy()
    far[:, :5] = 55.0  # the left half rendered at 55 units: veil, not seabed
    point_range = np.full(4, 4.2)
    assert view_quality("v", alpha, pts, rendered_range=near, point_range=point_range).point_depth == 1.0
    q = view_quality("v", alpha, pts, rendered_range=far, point_range=point_range)
    assert q.point_depth == 0.5 and q.point_coverage == 1.0  # covered, but not at the surface
    deep = view_quality("w", alpha, pts, rendered_range=np.full((10, 10), 55.0), point_range=point_range)
    collapsed, warnings = collapse_warnings([deep], 5000, 10_000)
    assert not collapsed and "drawn far behind" in warnings[0]


def test_far_share_catches_surface_drawn_far_behind_between_the_points():
    """Real RUIE sand: few points there, so point depth looks fine, but a quarter of the view renders at ~15x
    the points' distance, showing only the veil (restored black)."""
    alpha = np.ones((10, 10))
    pts = np.array([[7.5, 1.5], [8.5, 5.5], [7.5, 8.5]])  # points only on the right
    rng = np.full((10, 10), 10.0)
    rng[:, :3] = 150.0  # the left 30 % drawn far behind
    q = view_quality("v", alpha, pts, rendered_range=rng, point_range=np.array([9.5, 10.0, 10.5]))
    assert q.point_depth == 1.0 and abs(q.far_share - 0.3) < 1e-9
    collapsed, warnings = collapse_warnings([q], 5000, 10_000)
    assert not collapsed and "beyond 3x" in warnings[0] and "30%" in warnings[0]
    ok = view_quality("v", alpha, pts, rendered_range=np.full((10, 10), 10.0),
                      point_range=np.array([9.5, 10.0, 10.5]))
    assert ok.far_share == 0.0


def _textured(rng: np.random.Generator, h: int, w: int, contrast: float) -> np.ndarray:
    """A grey veil with a blocky texture of ``contrast`` (the seabed) and faint pixel noise (the camera)."""
    blocks = rng.uniform(-contrast, contrast, (h // 4, w // 4)).repeat(4, 0).repeat(4, 1)
    return np.repeat((0.4 + blocks + rng.normal(0, 0.002, (h, w)))[..., None], 3, -1)


def test_uncovered_detail_flags_seabed_given_up_as_veil_not_open_water():
    """Photo-textured medium water, the steep oblique views: their far half (8-16 m) left uncovered and rendered as
    the uniform veil although the photo still shows its texture. Open water (smooth) uncovered is no warning."""
    rng = np.random.default_rng(0)
    h, w = 40, 60
    photo = _textured(rng, h, w, 0.03)
    alpha = np.ones((h, w))
    alpha[:16] = 0.0  # the top 40 % uncovered
    predicted = photo.copy()
    predicted[:16] = 0.4  # ... and predicted as the flat veil
    predicted[16:] += rng.normal(0, 0.004, (h - 16, w, 1))  # the covered part fits up to a small error
    q = view_quality("far", alpha, np.zeros((0, 2)), predicted=predicted, photo=photo)
    assert q.uncovered_detail is not None and q.uncovered_detail > 0.3
    collapsed, warnings = collapse_warnings([q], 5000, 10_000)
    assert not collapsed and "far" in warnings[0] and "open water" in warnings[0]

    water = photo.copy()
    water[:16] = 0.4 + rng.normal(0, 0.002, (16, w, 1))  # the top is open water: smooth, only noise
    q = view_quality("open", alpha, np.zeros((0, 2)), predicted=predicted, photo=water)
    assert q.uncovered_detail is not None and q.uncovered_detail < 0.01
    assert collapse_warnings([q], 5000, 10_000) == (False, [])
    covered = view_quality("all", np.ones((h, w)), np.zeros((0, 2)), predicted=predicted, photo=photo)
    assert covered.uncovered_detail == 0.0
    assert view_quality("none", np.zeros((h, w)), np.zeros((0, 2)), predicted=predicted,
                        photo=photo).uncovered_detail is None  # nothing covered: no reference spread


def test_box_mean_matches_a_direct_window_mean():
    from pipeline.train.quality import box_mean

    x = np.random.default_rng(1).normal(size=(9, 13))
    got = box_mean(x, 3)
    pad = np.pad(x, 1, mode="edge")
    ref = np.array([[pad[i:i + 3, j:j + 3].mean() for j in range(13)] for i in range(9)])
    assert np.allclose(got, ref)


def test_a_veil_drawn_over_most_of_the_detail_is_a_lost_view_with_a_medium():
    rng = np.random.default_rng(1)
    h, w = 40, 60
    photo = _textured(rng, h, w, 0.03)
    alpha = np.ones((h, w))
    alpha[:28] = 0.0  # 70 % uncovered ...
    predicted = photo.copy()
    predicted[:28] = 0.4  # ... and drawn as the flat veil over the seabed's texture
    predicted[28:] += rng.normal(0, 0.004, (h - 28, w, 1))
    q = view_quality("eaten", alpha, np.zeros((0, 2)), predicted=predicted, photo=photo)
    assert q.uncovered_detail is not None and q.uncovered_detail > 0.5
    assert lost_view(q, medium=True) and not lost_view(q, medium=False)
    collapsed, warnings = collapse_warnings([q, q], 5000, 10_000)
    assert collapsed and "2 of 2 training views lost their scene" in warnings[0]


def test_a_faint_plain_model_that_renders_its_photos_is_not_lost():
    """AIMS Erub in 3dgs: a dark reef drawn faint over the black background (alpha ~0.25, under 5 % of the pixels
    at 0.5 in 15 of 22 views) renders its photos at 37-40 dB; the job failed as "collapsed". In plain splatting a
    view is lost only where the prediction misses what the photo shows; a model gone transparent renders the black
    background and still is. With a medium the rule is unchanged (a transparent medium model shows the veil)."""
    photo = np.full((8, 8, 3), 0.12)
    photo[::2] = 0.2  # texture
    faint = np.full((8, 8), 0.25)
    healthy = view_quality("f", faint, np.zeros((0, 2)), predicted=photo * 0.98, photo=photo)
    gone = view_quality("g", np.zeros((8, 8)), np.zeros((0, 2)), predicted=np.zeros((8, 8, 3)), photo=photo)
    assert healthy.uncovered_content == 1.0 and healthy.uncovered_missed == 0.0 and gone.uncovered_missed == 1.0
    assert not lost_view(healthy, medium=False) and lost_view(gone, medium=False)
    collapsed, warnings = collapse_warnings([healthy] * 3, 50_000, 100_000, medium=False)
    assert not collapsed and len(warnings) == 1 and "drawn faint" in warnings[0]
    assert collapse_warnings([gone] * 3, 50_000, 100_000, medium=False)[0]
    assert lost_view(healthy, medium=True) and collapse_warnings([healthy] * 3, 50_000, 100_000)[0]
