"""The colour-consistency score on sightings whose change with range is known."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluate.consistency import MIN_POINTS, colour_consistency
from pipeline.medium.drift import point_slopes, robust_line
from pipeline.medium.estimate import Observations
from pipeline.restore.consistency import photo_positions
from pipeline.scene.records import Camera, LensCamera, Sightings, View


def _sightings(n_points: int = 400, per_point: int = 5, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point [M], range [M], the points' true colours [P, 3]): each point seen at ranges 2-4."""
    rng = np.random.default_rng(seed)
    point = np.repeat(np.arange(n_points), per_point)
    r = rng.uniform(2.0, 4.0, point.size)
    J = rng.uniform(0.1, 0.9, (n_points, 3))
    return point, r, J


def _observe(point, r, J, gain, offset, noise=0.0, seed=1) -> Observations:
    """Colour = J·(1 + gain·(r − 3)) + offset·(r − 3) + noise, per channel (gain, offset [3])."""
    d = (r - 3.0)[:, None]
    c = J[point] * (1 + np.asarray(gain) * d) + np.asarray(offset) * d
    c = c + np.random.default_rng(seed).normal(0, noise, c.shape)
    return Observations(point, r, c)


def test_known_slope_is_recovered():
    point, r, J = _sightings()
    gain, offset = np.array([-0.3, -0.1, 0.0]), np.array([0.05, 0.0, 0.02])
    obs = _observe(point, r, J, gain, offset, noise=0.01)
    res = colour_consistency(obs, obs)
    assert res["defined"] and 390 <= res["n_points"] <= 400  # a point whose 5 ranges fell within 1.1x is left out
    np.testing.assert_allclose(res["photo"]["slope_gain"], gain, atol=0.01)
    np.testing.assert_allclose(res["photo"]["slope_offset"], offset, atol=0.005)
    # drift = RMS over the points of (gain·level + offset) · (r90 − r10)
    s = point_slopes(obs)
    q10, q90 = np.percentile(r, [10, 90])
    expected = np.sqrt(np.mean((gain * s.level + offset) ** 2, axis=0)) * (q90 - q10)
    np.testing.assert_allclose(res["photo"]["drift"], expected, rtol=0.05, atol=0.002)
    assert res["share"] == pytest.approx(1.0)


def test_no_trend_scores_near_zero_and_ranks_below_a_trend():
    point, r, J = _sightings()
    trend = _observe(point, r, J, [-0.3, -0.2, -0.1], [0.0, 0.0, 0.0], noise=0.02)
    flat = _observe(point, r, J, [0.0] * 3, [0.0] * 3, noise=0.02)
    res = colour_consistency(trend, flat)
    assert res["defined"]
    assert res["photo_score"] > 0.3
    assert res["restored_score"] < 0.03
    assert res["share"] < 0.1


def test_gain_and_offset_of_the_whole_restoration_change_nothing():
    """A darker, brighter or flatter copy of a restoration scores the same: no reward for shrinking colours."""
    point, r, J = _sightings()
    photo = _observe(point, r, J, [-0.3, -0.2, -0.1], [0.02, 0.0, 0.0], noise=0.01)
    restored = _observe(point, r, J, [-0.1, 0.05, 0.0], [0.0, 0.01, 0.0], noise=0.01, seed=2)
    flattened = Observations(point, r, 0.5 + 0.3 * (restored.colour - 0.5))
    a, b = colour_consistency(photo, restored), colour_consistency(photo, flattened)
    assert a["defined"] and b["defined"]
    assert b["restored_score"] == pytest.approx(a["restored_score"], rel=1e-6)


def test_a_constant_restoration_is_undefined_not_perfect():
    point, r, J = _sightings()
    photo = _observe(point, r, J, [-0.3, -0.2, -0.1], [0.0] * 3, noise=0.01)
    for value in (0.0, 0.5):
        res = colour_consistency(photo, Observations(point, r, np.full_like(photo.colour, value)))
        assert not res["defined"] and res["share"] is None
        assert "contrast" in res["reason"]
    # one channel nearly flattened (to 10 % of its contrast) is enough
    squashed = photo.colour.copy()
    squashed[:, 2] = 0.5 + 0.1 * (squashed[:, 2] - 0.5)
    res = colour_consistency(photo, Observations(point, r, squashed))
    assert not res["defined"] and "channel B (10% of the photos', 0% of its sightings clipped" in res["reason"]
    saturated = np.clip(photo.colour * [1.0, 1.0, 20.0], 0, 1)  # blue amplified into the clip
    res = colour_consistency(photo, Observations(point, r, saturated))
    assert not res["defined"] and res["clipped"][2] > 0.9 and "channel B" in res["reason"]


def test_outlier_points_do_not_pull_the_line():
    """A tenth of the points change wildly with range (moving things, mismatches): the fit keeps to the rest."""
    point, r, J = _sightings(n_points=500)
    obs = _observe(point, r, J, [-0.2, -0.2, -0.2], [0.0] * 3, noise=0.01)
    wild = np.isin(point, np.arange(50))
    c = obs.colour.copy()
    c[wild] += np.random.default_rng(3).normal(0, 0.5, (int(wild.sum()), 1)) * (r[wild, None] - 3.0)
    res = colour_consistency(obs, Observations(point, r, c))
    np.testing.assert_allclose(res["restored"]["slope_gain"], [-0.2] * 3, atol=0.02)
    assert res["share"] == pytest.approx(1.0, abs=0.1)


def test_robust_line_exact_on_clean_points():
    x = np.linspace(0, 1, 50)
    a, b = robust_line(x, 2.0 * x - 0.5, np.ones(50))
    assert (a, b) == (pytest.approx(2.0), pytest.approx(-0.5))


def test_too_few_points_or_no_range_spread_is_undefined():
    point, r, J = _sightings(n_points=MIN_POINTS - 1)
    obs = _observe(point, r, J, [-0.3] * 3, [0.0] * 3)
    res = colour_consistency(obs, obs)
    assert not res["defined"] and f"only {MIN_POINTS - 1} sparse points" in res["reason"]
    point, r, J = _sightings()
    same = Observations(point, 3.0 + 0.01 * (r - 3.0), J[point])  # every point seen from (nearly) one range
    res = colour_consistency(same, same)
    assert not res["defined"] and res["n_points"] == 0
    with pytest.raises(ValueError, match="same sightings"):
        colour_consistency(obs, Observations(point[:-1], r[:-1], obs.colour[:-1]))


def test_sightings_are_carried_into_the_distorted_photo():
    """A photo pixel, undistorted into the PINHOLE image by the lens, comes back to where it was."""
    lens = LensCamera("SIMPLE_RADIAL", 400, 300, (320.0, 200.0, 150.0, -0.12))
    cam = Camera(380, 286, 320.0, 320.0, 190.0, 143.0)  # the undistorted crop: another size and centre
    view = View("a.png", cam, np.eye(3), np.zeros(3))
    uv = np.array([[0.5, 0.5], [200.0, 150.0], [390.2, 12.7], [17.0, 280.5]])
    rays = lens.colmap().cam_from_img(uv)
    xy = np.stack([cam.fx * rays[:, 0] + cam.cx, cam.fy * rays[:, 1] + cam.cy], 1)
    back = photo_positions(view, Sightings(np.arange(4), xy / 2, cam.width // 2), lens)  # tracks at half size
    np.testing.assert_allclose(back, uv, atol=1e-6)


def test_the_report_says_why_a_job_has_no_score():
    from pipeline.export.report import consistency_of

    assert consistency_of(None)["reason"].startswith("the job has no restored photos")
    assert consistency_of({"restored": 0, "note": "mode 3dgs models no water"}) == {
        "defined": False, "reason": "mode 3dgs models no water"}
    assert "re-run it" in consistency_of({"restored": 3, "views": []})["reason"]  # restored before the score existed
    block = {"defined": True, "reason": None, "share": 0.2}
    assert consistency_of({"restored": 3, "consistency": block}) is block
