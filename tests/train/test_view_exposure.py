"""The training views' exposure (pipeline.train.exposure): a step moves only the view that was rendered, the set
stays mean-neutral, the state round-trips, and a short fit recovers a view's gain from its photo."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.scene.exposure import exposed
from pipeline.train.exposure import ViewExposure, exposure_record


def test_a_step_moves_one_view_and_keeps_the_mean():
    ex = ViewExposure(4, "srgb", lr=0.01, weight=0.0, iterations=100)
    target = torch.full((8, 8, 3), 0.5)
    ex.correct(2, target).sum().backward()
    ex.step(1)
    lg = np.log(ex.gains())
    np.testing.assert_allclose(lg.mean(0), 0, atol=1e-7)
    moved = lg - lg[0]  # views 0, 1, 3 shift together by the re-centring only
    assert np.abs(moved[[1, 3]]).max() < 1e-7 and np.abs(moved[2]).min() > 1e-3


def test_state_round_trip():
    ex = ViewExposure(3, "linear", lr=0.01, weight=0.0, iterations=10, init=np.log([[1.1, 1, 1], [1, 0.9, 1],
                                                                                    [1, 1, 1]]))
    other = ViewExposure(3, "linear", lr=0.01, weight=0.0, iterations=10)
    other.load_state_dict(ex.state_dict())
    np.testing.assert_allclose(other.gains(), ex.gains())


def test_gains_fitted_to_photos_of_one_scene():
    """Two views of the same image, taken at gains 1.25 and 0.8 (mean-neutral): the gains are found."""
    scene = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(0)) * 0.6 + 0.1
    true = np.log([[1.25, 1.2, 1.3], [0.8, 1 / 1.2, 1 / 1.3]])
    photos = [torch.from_numpy(exposed(scene.numpy().astype(np.float64), lg, "srgb")).float() for lg in true]
    ex = ViewExposure(2, "srgb", lr=0.02, weight=1e-4, iterations=400)
    for it in range(400):
        i = it % 2
        (ex.correct(i, photos[i]) - scene).abs().mean().backward()
        ex.step(it + 1)
    np.testing.assert_allclose(np.log(ex.gains()), true, atol=0.01)
    rec = exposure_record(["a", "b"], ex.gains())
    assert set(rec["views"]) == {"a", "b"} and abs(rec["max_deviation"] - 0.3) < 0.02


def test_the_surveys_fall_off_is_divided_out_of_the_photo_and_put_back_on_the_render():
    """Training compares the model with the photo at even light (the fall-off divided out with the gains); what
    compares the model with a photo later puts it back (``as_photographed``): the round trip is the photo."""
    from pipeline.medium.fall_off import as_photographed, fall_off_to_remove, log_fall_off_map
    from pipeline.train.photo_exposure import removed_fall_off

    theta = np.array([0.1, -0.2, -0.3, -0.2, 0.05])
    fall = fall_off_to_remove({"exposure_field": theta.tolist(), "field_span": 2.0})
    even = np.random.default_rng(0).uniform(0.1, 0.6, (12, 16, 3))
    lg = np.log([[1.1, 1.0, 0.9], [1 / 1.1, 1.0, 1 / 0.9]])
    photo = exposed(even, lg[1] + log_fall_off_map(16, 12, theta)[..., None], "srgb")
    assert np.abs(photo - even).max() > 0.1  # the corners are much darker
    ex = ViewExposure(2, "srgb", lr=0.0, weight=0.0, iterations=10, init=lg, fall_off=fall)
    got = ex.correct(1, torch.from_numpy(photo).float()).numpy()
    np.testing.assert_allclose(got, even, atol=1e-5)
    record = ex.record(["a", "b"])
    assert record["fall_off"]["removed"]
    np.testing.assert_allclose(as_photographed(even, lg[1], removed_fall_off(record)), photo, atol=1e-6)
    plain = ViewExposure(2, "srgb", lr=0.0, weight=0.0, iterations=10, init=lg)  # no fall-off measured: left in
    assert plain.record(["a", "b"])["fall_off"] is None and removed_fall_off(plain.record(["a", "b"])) is None
