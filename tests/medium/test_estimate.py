"""The water measured from the sparse points before training (pipeline.medium.estimate)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import SynthConfig
from pipeline.medium.estimate import Observations, fit_medium, gather_observations
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.synth.procedural import generate_scene
from pipeline.synth.water import WATER_PRESETS


def _exact_observations(water, n_points=400, per_point=6, seed=0) -> Observations:
    rng = np.random.default_rng(seed)
    point = np.repeat(np.arange(n_points), per_point)
    r = rng.uniform(1.0, 6.0, point.size)
    J = rng.uniform(0.05, 0.9, (n_points, 3))
    bd, bb, binf = (np.asarray(x) for x in (water.beta_D, water.beta_B, water.B_inf))
    colour = J[point] * np.exp(-bd * r[:, None]) + binf * (1 - np.exp(-bb * r[:, None]))
    return Observations(point, r, colour)


@pytest.mark.parametrize("preset", ["clear", "medium", "turbid"])
def test_fit_recovers_the_model_it_assumes(preset):
    water = WATER_PRESETS[preset]
    est = fit_medium(_exact_observations(water))
    assert est is not None and est.residual < 1e-4
    np.testing.assert_allclose(est.beta_D, water.beta_D, rtol=0.02)
    np.testing.assert_allclose(est.beta_B, water.beta_B, rtol=0.05)
    np.testing.assert_allclose(est.B_inf, water.B_inf, rtol=0.05)


def test_too_few_points_seen_twice_gives_no_estimate():
    obs = _exact_observations(WATER_PRESETS["medium"], n_points=30)
    assert fit_medium(obs) is None
    single = Observations(np.arange(500), np.full(500, 2.0), np.full((500, 3), 0.3))
    assert fit_medium(single) is None


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = {}
    for preset in ("none", "medium"):
        root = generate_scene(SynthConfig(views=12, width=128, height=96, preset=preset, seed=5),
                              tmp_path_factory.mktemp(preset))
        scene = load_scene(root)
        out[preset] = (scene, [read_image(root / "images" / v.name) for v in scene.views])
    return out


def test_sightings_are_the_tracks_of_the_model(generated):
    scene, _ = generated["medium"]
    assert scene.sightings is not None and set(scene.sightings) == {v.name for v in scene.views}
    v = scene.views[3]
    s = scene.sightings[v.name]
    cam = scene.points[s.point] @ v.R.T + v.t
    uv = np.stack([v.camera.fx * cam[:, 0] / cam[:, 2] + v.camera.cx,
                   v.camera.fy * cam[:, 1] / cam[:, 2] + v.camera.cy], axis=1)
    assert len(s.point) > 100 and np.abs(uv - s.xy).max() < 0.01  # the generator's tracks are exact
    sub = scene.subset(scene.views[:2])
    assert sub.sightings is scene.sightings and len(sub.views) == 2


@pytest.mark.parametrize("use_tracks", [True, False])
def test_generated_medium_water_is_measured(generated, use_tracks):
    scene, images = generated["medium"]
    obs = gather_observations(scene.points, scene.views, images, scene.sightings if use_tracks else None)
    est = fit_medium(obs)
    assert est is not None and est.n_points > 500
    truth = WATER_PRESETS["medium"].beta_D  # true metric cameras: scene units are metres
    # The generator's points are random surface samples, not features: a pixel's colour there depends on how
    # much texture it covers, which changes with range (measured: 4-25 % high per channel; SfM keypoints of a
    # 24-view scene: within 0-23 %).
    np.testing.assert_allclose(est.beta_D, truth, rtol=0.3)
    assert est.beta_D[0] > est.beta_D[1] > est.beta_D[2]


def test_no_water_measures_almost_no_attenuation(generated):
    scene, images = generated["none"]
    est = fit_medium(gather_observations(scene.points, scene.views, images, scene.sightings))
    assert est is not None
    assert max(est.beta_D) < 0.05, est  # 1/m; the medium preset's weakest channel is 0.11


def _narrow(water, lo, hi, noise, seed=0, n_points=400, per_point=6) -> Observations:
    rng = np.random.default_rng(seed)
    point = np.repeat(np.arange(n_points), per_point)
    r = rng.uniform(lo, hi, point.size)
    J = rng.uniform(0.05, 0.9, (n_points, 3))
    bd, bb, binf = (np.asarray(x) for x in (water.beta_D, water.beta_B, water.B_inf))
    colour = J[point] * np.exp(-bd * r[:, None]) + binf * (1 - np.exp(-bb * r[:, None]))
    return Observations(point, r, colour + rng.normal(0.0, noise, colour.shape))


def test_uncertainty_is_reported_and_shrinks_with_the_range_spread():
    water = WATER_PRESETS["medium"]
    wide = fit_medium(_narrow(water, 1.0, 6.0, 0.01), (1.6, 0.6, 0.5))
    narrow = fit_medium(_narrow(water, 1.8, 2.4, 0.03), (1.6, 0.6, 0.5))
    for est in (wide, narrow):
        u = est.uncertainty
        assert set(u) >= {"beta_D", "beta_B", "B_inf", "prior", "scale"}
        assert all(len(u[k]["sigma"]) == 3 and len(u[k]["source"]) == 3 for k in ("beta_D", "beta_B", "B_inf"))
    assert all(s < 0.05 for s in wide.uncertainty["beta_D"]["data_sigma"])  # 1-6 m pins β_D to a few %
    assert all(n > w for n, w in zip(narrow.uncertainty["beta_D"]["data_sigma"],
                                     wide.uncertainty["beta_D"]["data_sigma"], strict=True))
    assert wide.uncertainty["beta_D"]["source"] == ["measured"] * 3
    np.testing.assert_allclose(wide.beta_D, water.beta_D, rtol=0.03)  # the prior does not move measured values


def test_a_narrow_range_falls_back_on_the_water_type_and_physics_not_on_a_bound():
    """Sightings over 1.8-2.4 m cannot separate the veil's saturation from its strength: least squares puts β_B
    near zero (a veil that never saturates, B∞ large); the water type's prior and c >= b keep it physical."""
    water = WATER_PRESETS["medium"]
    obs = _narrow(water, 1.8, 2.4, 0.03)
    free = fit_medium(obs, (1.6, 0.6, 0.5), prior=False)
    held = fit_medium(obs, (1.6, 0.6, 0.5))
    err = lambda est: np.abs(np.log(np.asarray(est.beta_B) / np.asarray(water.beta_B)))  # noqa: E731
    assert err(held).max() < 0.8 and err(free).max() > 1.5, (held.beta_B, free.beta_B)
    assert all(b <= d * 1.2 for b, d in zip(held.beta_B, held.beta_D, strict=True))  # β_B <= β_D (c >= b)


def test_no_range_information_is_not_determined_but_prior():
    """Every point seen at one range: nothing about range can be measured; the coefficients are the prior's."""
    rng = np.random.default_rng(1)
    point = np.repeat(np.arange(300), 3)
    obs = Observations(point, np.full(point.size, 2.0) + rng.normal(0, 1e-6, point.size),
                       np.clip(rng.uniform(0.1, 0.6, (300, 3))[point] + rng.normal(0, 0.01, (point.size, 3)), 0, 1))
    est = fit_medium(obs, (1.6, 0.6, 0.5))
    assert est is not None
    assert "prior" in est.uncertainty["beta_D"]["source"]


def _torch_twin_inputs(seed=3):
    obs = _narrow(WATER_PRESETS["turbid"], 0.5, 5.0, 0.02, seed=seed)
    pid, inv = np.unique(obs.point, return_inverse=True)
    return inv, len(pid), obs.range, obs.colour[:, 0]


@pytest.mark.parametrize("theta", [(-1.3, -2.9, -4.4), (0.5, 0.2, -1.0), (-0.2, -0.5, 1.5)])
def test_closed_form_gradient_matches_the_autograd_twin(theta):
    """The fit's misfit and gradient against ``_channel_loss`` under autograd (which differentiates through the
    eliminated J too); the points include clamped J (black and saturated surfaces)."""
    import torch

    from pipeline.medium.estimate import _channel_loss, _channel_loss_grad

    inv, n, r, I = _torch_twin_inputs()  # noqa: E741
    I = I.copy()  # noqa: E741
    I[inv < 40] = 0.0  # black points: J clamps at 0
    I[(inv >= 40) & (inv < 80)] = 1.0  # saturated: J clamps at 1 where the water dims less
    th = np.asarray(theta, dtype=np.float64)
    loss, grad = _channel_loss_grad(th, inv, n, r, I)
    t = torch.tensor(th, requires_grad=True)
    ref, J = _channel_loss(t, torch.as_tensor(inv), n, torch.as_tensor(r), torch.as_tensor(I))
    (ref_grad,) = torch.autograd.grad(ref, t)
    assert ((J == 0) | (J == 1)).sum() >= 40  # clamps are exercised
    np.testing.assert_allclose(loss, float(ref.detach()), rtol=1e-12)
    np.testing.assert_allclose(grad, ref_grad.numpy(), rtol=1e-8, atol=1e-14)


def test_a_fit_on_its_bound_is_a_failed_measurement_and_the_prior_stands():
    """Issue 39's real green video: colours that grow with range without saturating (an exposure that follows the
    range) put least squares' B∞ on its bound (0.953, grey) with β_D ≈ 0, read downstream as "no water". That is
    not a measurement: the channel says why and takes the water type's β (optical depth / median range)."""
    rng = np.random.default_rng(0)
    point = np.repeat(np.arange(400), 6)
    r = rng.uniform(2.0, 5.0, point.size)
    J = rng.uniform(0.05, 0.6, (400, 3))
    colour = J[point] * np.exp(-0.01 * r[:, None]) + 0.08 * r[:, None] + rng.normal(0, 0.01, (point.size, 3))
    obs = Observations(point, r, colour)
    free = fit_medium(obs, (0.8, 0.3, 0.25), prior=False)
    assert min(free.B_inf) > 0.95 and max(free.beta_D) < 1e-3  # the degenerate least-squares fit
    est = fit_medium(obs, (0.8, 0.3, 0.25))
    failed = est.uncertainty["failed"]
    assert all(f is not None and "upper bound" in f for f in failed), failed
    assert est.uncertainty["beta_D"]["source"] == ["prior"] * 3
    np.testing.assert_allclose(est.beta_D, np.array([0.8, 0.3, 0.25]) / est.median_range, rtol=1e-6)
    assert max(est.B_inf) < 0.95 and est.effect() > 0.1  # water, not "no water"


def test_a_sound_fit_has_no_failure():
    est = fit_medium(_exact_observations(WATER_PRESETS["medium"]))
    assert est.uncertainty["failed"] == [None, None, None]
