"""The paper's losses with the physics made right: signs, and what pushes against the "no water" solution."""

from __future__ import annotations

import pytest
import torch

from pipeline.config import SynthConfig
from pipeline.medium import losses as L
from pipeline.scene.records import ray_length_factor
from pipeline.synth.procedural import make_camera, synth_views
from pipeline.synth.water import WATER_PRESETS


def _depth_ramp(h=16, w=16) -> torch.Tensor:
    return torch.linspace(1.0, 6.0, w).expand(1, 1, h, w).contiguous()


def test_consistency_loss_prefers_backscatter_rising_with_depth():
    D = _depth_ramp()
    beta = torch.tensor([0.4, 0.2, 0.1]).reshape(1, 3, 1, 1)
    rising_b = 1 - torch.exp(-beta * D)
    falling_b = rising_b.flip(-1)  # the same values, but largest where the scene is nearest
    falling_a = torch.exp(-beta * D).flip(-1)  # and transmission rising with depth
    rising_a = torch.exp(-beta * D)
    good = L.consistency_loss(rising_a, rising_b, D, depth_scale=3.0)
    bad = L.consistency_loss(falling_a, falling_b, D, depth_scale=3.0)
    assert good < bad - 0.05
    # The printed eq. 9 (E[B_s·D] − E[A·D] + μ·MSE) ranks them the other way round: that is the sign error.
    def printed(a, b):
        return (b * D).mean() - (a * D).mean() + 0.1 * ((b + a - 1) ** 2).mean()
    assert printed(rising_a, rising_b) > printed(falling_a, falling_b)


@pytest.mark.parametrize("preset", ["clear", "medium", "turbid"])
def test_true_medium_beats_the_trivial_no_water_solution(preset):
    """Both decompositions reproduce the photo exactly; only the priors can tell them apart."""
    cfg = SynthConfig(views=6, width=64, height=48, preset=preset, noise_std=0.0, seed=4)
    _, views = synth_views(cfg)
    water = WATER_PRESETS[preset]
    ray = ray_length_factor(make_camera(cfg))
    w = L.LossWeights()
    for sv in views:
        r = torch.from_numpy(sv.depth * ray).float()[None, None]
        J = torch.from_numpy(sv.J).float().permute(2, 0, 1)[None]
        I = torch.from_numpy(sv.image).float().permute(2, 0, 1)[None]  # noqa: E741
        bd = torch.tensor(water.beta_D).reshape(1, 3, 1, 1)
        bb = torch.tensor(water.beta_B).reshape(1, 3, 1, 1)
        A = torch.exp(-bd * r)
        Bf = 1 - torch.exp(-bb * r)
        alpha = torch.ones_like(r)
        scale = float(r.median())
        B = torch.tensor(water.B_inf).reshape(1, 3, 1, 1) * Bf
        truth = L.total_loss(I, I, J, A, B, Bf, r, alpha, scale, w)
        zero = torch.zeros_like(Bf)
        trivial = L.total_loss(I, I, I, torch.ones_like(A), zero, zero, r, alpha, scale, w)
        assert truth["basic"] == trivial["basic"]  # photometrically indistinguishable
        assert truth["scattering"] == 0  # the true veil never exceeds the photo
        assert truth["attenuation"] < trivial["attenuation"]
        assert truth["ab"] < trivial["ab"]
        assert truth["total"] < trivial["total"]


def test_floater_loss_penalises_haze_not_solid_surfaces():
    solid = torch.ones(1, 1, 8, 8)
    empty = torch.zeros(1, 1, 8, 8)
    haze = torch.full((1, 1, 8, 8), 0.4)
    assert L.floater_loss(solid) == 0 and L.floater_loss(empty) == 0
    assert L.floater_loss(haze) == pytest.approx(0.24)


def test_multiscale_loss_counts_all_three_scales():
    a = torch.zeros(1, 3, 8, 8)
    b = torch.full((1, 3, 8, 8), 0.5)
    # L1 at full res 0.5, plus λ/3·(0.5 + 0.5 + 0.5) with box downsampling of a constant image.
    assert float(L.multiscale_loss(a, b, lam_ms=1.0)) == pytest.approx(1.0)


def test_edge_loss_is_zero_for_uniform_backscatter_on_flat_depth():
    D = torch.full((1, 1, 8, 8), 2.0)
    B = torch.full((1, 3, 8, 8), 0.3)
    assert float(L.edge_loss(B, D, 2.0)) == pytest.approx(0.0, abs=1e-7)
    rough = B + 0.1 * (torch.arange(8).float() % 2).reshape(1, 1, 1, 8)
    assert float(L.edge_loss(rough, D, 2.0)) > 0.01


def test_veil_bound_costs_only_backscatter_brighter_than_the_photo():
    photo = torch.full((1, 3, 4, 4), 0.3)
    ones = torch.ones(1, 1, 4, 4)
    assert float(L.scattering_prior(torch.full((1, 3, 4, 4), 0.2), photo, ones)) == 0.0
    assert float(L.scattering_prior(torch.full((1, 3, 4, 4), 0.5), photo, ones)) == pytest.approx(0.2)
    assert float(L.scattering_prior(torch.full((1, 3, 4, 4), 0.5), photo, ones * 0.5)) == 0.0


def test_surface_loss_holds_the_sparse_points_covered():
    alpha = torch.zeros(1, 1, 4, 5, requires_grad=True)
    pix = torch.tensor([0, 7, 19])
    loss = L.surface_loss(alpha, pix)
    assert float(loss.detach()) == 1.0
    loss.backward()
    g = alpha.grad.reshape(-1)
    assert torch.all(g[pix] < 0) and int((g != 0).sum()) == 3  # only the points' pixels are pushed, towards cover
    covered = torch.ones(1, 1, 4, 5)
    assert float(L.surface_loss(covered, pix)) == 0.0
    assert float(L.surface_loss(covered, torch.zeros(0, dtype=torch.long))) == 0.0


def test_point_depth_loss_pulls_the_surface_to_the_points():
    D = torch.full((1, 1, 4, 5), 50.0, requires_grad=True)  # a surface drawn far behind, where it shows only water
    pix, r = torch.tensor([3, 11]), torch.tensor([5.0, 5.0])
    loss = L.point_depth_loss(D, pix, r)
    assert abs(float(loss.detach()) - float(torch.log(torch.tensor(10.0)))) < 1e-5
    loss.backward()
    g = D.grad.reshape(-1)
    assert torch.all(g[pix] > 0) and int((g != 0).sum()) == 2  # descent brings those pixels nearer
    assert float(L.point_depth_loss(torch.full((1, 1, 4, 5), 5.0), pix, r)) == 0.0


def test_depth_band_loss_pulls_far_surfaces_in_and_never_uncovers():
    ref = torch.full((1, 1, 2, 2), 10.0)  # the neighbourhood's points predict 10
    D = torch.tensor([[[[10.0, 25.0, 150.0], [6.0, 150.0, 2.5]]]], requires_grad=True)
    alpha = torch.tensor([[[[1.0, 1.0, 1.0], [1.0, 0.0, 1.0]]]], requires_grad=True)
    loss = L.depth_band_loss(D, alpha, ref)
    loss.backward()
    g = D.grad.reshape(-1)
    # Up to 3x beyond (30) and anything nearer is free; 150 is pulled in; an uncovered pixel is free.
    assert g[2] > 0 and int((g != 0).sum()) == 1
    expected = float(torch.log(torch.tensor(5.0))) / 6
    assert abs(float(loss.detach()) - expected) < 1e-5
    assert alpha.grad is None or float(alpha.grad.abs().sum()) == 0.0  # covering less is no way out
    assert float(L.depth_band_loss(D.detach(), alpha.detach(), torch.zeros(0))) == 0.0


def test_depth_band_loss_pushes_near_surfaces_back_only_where_the_plane_fit_holds():
    ref = torch.full((1, 1, 2, 2), 10.0)  # the neighbourhood's points predict 10
    D = torch.tensor([[[[10.0, 8.5, 5.0], [5.0, 25.0, 150.0]]]], requires_grad=True)
    alpha = torch.tensor([[[[1.0, 1.0, 1.0], [0.0, 1.0, 1.0]]]], requires_grad=True)
    loss = L.depth_band_loss(D, alpha, ref, torch.ones(1, 1, 2, 2), near=1.25)
    loss.backward()
    g = D.grad.reshape(-1)
    # Down to 10/1.25 = 8 is free; 5 is pushed back, 150 pulled in; the uncovered near pixel is free.
    assert g[2] < 0 and g[5] > 0 and int((g != 0).sum()) == 2
    expected = (float(torch.log(torch.tensor(1.6))) + float(torch.log(torch.tensor(5.0)))) / 6
    assert abs(float(loss.detach()) - expected) < 1e-5
    assert alpha.grad is None or float(alpha.grad.abs().sum()) == 0.0
    # Where the fit ran out to the horizon (its range only a held bound), nearer is free, as without a mask.
    unfit = L.depth_band_loss(D.detach(), alpha.detach(), ref, torch.zeros(1, 1, 2, 2))
    assert abs(float(unfit) - float(L.depth_band_loss(D.detach(), alpha.detach(), ref))) < 1e-7
    assert abs(float(unfit) - float(torch.log(torch.tensor(5.0))) / 6) < 1e-5


def test_depth_band_loss_gradcheck():
    g = torch.Generator().manual_seed(3)
    D = (torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64) * 3 + 2.0).requires_grad_()  # all beyond the band
    alpha = torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64)
    ref = torch.full((1, 1, 2, 2), 0.4, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d: L.depth_band_loss(d, alpha, ref), (D,), eps=1e-6, atol=1e-5)
    near = (torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64) * 0.15 + 0.05).requires_grad_()  # all nearer
    fitted = torch.tensor([[[[1.0, 0.0], [1.0, 1.0]]]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d: L.depth_band_loss(d, alpha, ref, fitted), (near,), eps=1e-7, atol=1e-5)


def test_point_range_map_follows_the_points_neighbourhood():
    from types import SimpleNamespace

    from pipeline.medium.term import point_range_map

    W, H = 200, 100
    view = SimpleNamespace(camera=SimpleNamespace(width=W, height=H))
    xs = torch.randint(0, W, (400,), generator=torch.Generator().manual_seed(0))
    ys = torch.randint(0, H, (400,), generator=torch.Generator().manual_seed(1))
    ranges = torch.where(xs < W // 2, 4.0, 12.0)  # near on the left, far on the right
    m = point_range_map(view, ys * W + xs, ranges).range
    assert m.shape[:2] == (1, 1) and m.shape[-1] <= 96 and torch.isfinite(m).all()
    assert torch.allclose(m[..., :, :10], torch.tensor(4.0)) and torch.allclose(m[..., :, -10:], torch.tensor(12.0))
    assert point_range_map(view, torch.zeros(0, dtype=torch.long), torch.zeros(0)).range.numel() == 0


def _oblique_points(W: int, H: int, horizon_row: float):
    """Sparse points in the lower half of an oblique view of flat seabed whose horizon is at ``horizon_row``
    (1/r linear in the row, 0 at the horizon): (pixels, ranges, 1/r as a function of the row)."""
    g = torch.Generator().manual_seed(0)
    xs, ys = torch.randint(0, W, (300,), generator=g), torch.randint(H // 2, H, (300,), generator=g)
    inv_r = lambda y: 0.3 * ((y.double() + 0.5) - horizon_row) / H  # noqa: E731
    return ys * W + xs, (1 / inv_r(ys)).float(), inv_r


def test_point_range_map_follows_a_plane_beyond_its_points():
    """An oblique view of flat seabed: SfM found points only in the near (lower) half; the far half's range is
    the plane's, not the nearest points' (1/r of a plane is linear in the pixel)."""
    from types import SimpleNamespace

    from pipeline.medium.term import point_range_map

    W, H = 160, 120
    view = SimpleNamespace(camera=SimpleNamespace(width=W, height=H))
    pixels, ranges, inv_r = _oblique_points(W, H, horizon_row=-H / 15)  # 1/r = 0.02 + 0.3 (y + 0.5) / H: 3..50
    m = point_range_map(view, pixels, ranges).range
    cell = H / m.shape[-2]
    rows = torch.arange(m.shape[-2])
    truth = 1 / inv_r((rows + 0.5) * cell - 0.5)
    got = m[0, 0].median(dim=1).values.double()
    assert torch.all((got / truth - 1).abs()[rows * cell >= H // 2] < 0.1)  # close where the points are
    far = rows * cell < H // 4
    from pipeline.medium.losses import DEPTH_BAND

    # It followed the slope: the true far seabed is within the band, where depth_band_loss leaves it alone (the
    # nearest points' own range, 3-6, would have put it 8x too far).
    assert torch.all(truth[far] < DEPTH_BAND * got[far]), (got[far], truth[far])


def test_cover_range_map_predicts_the_seabed_in_sight_and_not_the_sky():
    """Below the horizon the plane's range is kept; above it (open water) and where the plane runs out to a
    range the points never came near, nothing is predicted."""
    from types import SimpleNamespace

    from pipeline.medium.term import COVER_MAX_RANGE, cover_range_map, point_range_map

    W, H = 160, 120
    view = SimpleNamespace(camera=SimpleNamespace(width=W, height=H))
    pixels, ranges, inv_r = _oblique_points(W, H, horizon_row=30.0)
    rm = point_range_map(view, pixels, ranges)
    cover = cover_range_map(rm, ranges)[0, 0]
    rows = (torch.arange(cover.shape[0]) + 0.5) * (H / cover.shape[0]) - 0.5
    sky = rows < 25  # above the horizon (row 30), with a margin for the fit's ridge
    assert torch.isinf(cover[sky]).all()
    assert not rm.fitted[0, 0][sky].any()  # the held bound, not a fit
    limit = COVER_MAX_RANGE * float(ranges.double().quantile(0.95))
    truth = 1 / inv_r(rows)
    seen = (rows >= H // 2)
    assert torch.isfinite(cover[seen]).all()
    assert torch.allclose(cover[seen].median(dim=1).values.double(), truth[seen], rtol=0.1)
    assert torch.isinf(cover[rm.range[0, 0] >= limit]).all()
    beyond = (truth > 3 * limit) & ~sky  # just below the horizon: too far out to trust the plane
    assert beyond.any() and torch.isinf(cover[beyond]).float().mean() > 0.9


def test_cover_weight_follows_the_water():
    from pipeline.medium.term import COVER_TRANSMISSION, cover_weight

    r = torch.tensor([[[[1.0, 10.0, 20.0, float("inf")]]]])
    lo, hi = COVER_TRANSMISSION
    w = cover_weight(r, torch.tensor(0.1))
    a = torch.exp(-0.1 * r)
    assert torch.allclose(w, ((a - lo) / (hi - lo)).clamp(0, 1))
    assert w[0, 0, 0, 0] == 1.0 and w[0, 0, 0, -1] == 0.0  # in clear sight: full; no surface predicted: none
    assert cover_weight(r, torch.tensor(1.0))[0, 0, 0, 1:].eq(0).all()  # murky: the far seabed is not asked for
    # Per channel, the clearest decides: red strangled (β 1.0) but green clear (0.1) still shows the seabed.
    assert torch.equal(cover_weight(r, torch.tensor([1.0, 0.1, 0.5])), w)


def test_cover_loss_pulls_alpha_up_where_the_surface_is_in_sight():
    alpha = torch.rand(1, 1, 8, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    alpha.requires_grad_(True)
    weight = torch.zeros(1, 1, 4, 6, dtype=torch.float64)
    weight[..., :, :3] = 1.0  # a surface in sight on the left half only
    loss = L.cover_loss(alpha, weight)
    loss.backward()
    assert (alpha.grad[..., :, :5] < 0).all()  # descent raises alpha there
    assert (alpha.grad[..., :, 7:] == 0).all()  # and leaves open water alone
    assert L.cover_loss(torch.ones(1, 1, 8, 12), torch.ones(1, 1, 4, 6)) == 0
    assert L.cover_loss(alpha, torch.zeros(0)) == 0
    a = alpha.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: L.cover_loss(x, weight), (a,), eps=1e-6, atol=1e-5)
