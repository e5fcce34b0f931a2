"""Each hot op against its slow twin."""

import numpy as np

from pipeline.restore.dewater import dewater, dewater_reference, local_misfit, local_misfit_reference
from pipeline.restore.guided import fast_guided_filter, fill_invalid, guided_filter, guided_filter_reference
from pipeline.restore.records import MediumMaps
from pipeline.restore.sample import sample_maps, sample_maps_reference
from pipeline.scene.records import Camera


def test_guided_filter_matches_reference():
    rng = np.random.default_rng(0)
    g, p = rng.random((37, 53)), rng.random((37, 53)) * 10 + 5
    for r in (1, 4, 30):
        assert np.abs(guided_filter(g, p, r, 1e-3) - guided_filter_reference(g, p, r, 1e-3)).max() < 2e-5
    assert np.abs(fast_guided_filter(g, p, 4, 1e-3, 1) - guided_filter(g, p, 4, 1e-3)).max() < 2e-5


def test_sampling_matches_reference():
    rng = np.random.default_rng(1)
    cam = Camera(20, 15, 18.0, 17.0, 10.3, 7.4)
    maps = rng.random((15, 20, 2))
    xn, yn = rng.uniform(-0.8, 0.8, (9, 11)), rng.uniform(-0.6, 0.6, (9, 11))
    a, ia = sample_maps(maps, xn, yn, cam)
    b, ib = sample_maps_reference(maps, xn, yn, cam)
    assert np.abs(a - b).max() < 1e-5 and (ia == ib).all() and (~ia).any()


def test_fill_keeps_valid_and_fills_all():
    rng = np.random.default_rng(2)
    x, v = rng.random((31, 17, 2)), rng.random((31, 17)) > 0.9
    f = fill_invalid(x, v)
    assert np.isfinite(f).all() and (f[v] == x[v]).all() and f.min() >= x[v].min() and f.max() <= x[v].max()


def test_dewater_matches_reference_both_spaces_and_map_coefficients():
    rng = np.random.default_rng(3)
    img = rng.random((13, 29, 3)).astype(np.float32)
    r = rng.uniform(0, 20, (13, 29)).astype(np.float32)
    surf = rng.random((13, 29)) > 0.2
    for kA, kB in (([0.3, 0.1, 0.05], [0.2, 0.1, 0.1]), (rng.random((13, 29, 3)), rng.random((13, 29, 3)))):
        sigma = np.array([[0.1, 0.2, np.nan], [0.3, 0.05, 0.1], [0.2, 0.2, 0.4]])  # NaN: not determined
        m = MediumMaps(np.asarray(kA, np.float32), np.asarray(kB, np.float32), np.array([0.1, 0.2, 0.3]), sigma)
        noise2 = np.array([1e-4, 4e-5, 2e-4])
        for space, prior in (("srgb", None), ("linear", None), ("srgb", rng.random((13, 29, 3)).astype(np.float32)),
                             ("linear", rng.random((13, 29, 3)).astype(np.float32))):
            lam2 = None if prior is None else np.array([0.01, 0.2, 0.0])  # the last under the floor: floored
            J, c, n = dewater(img, r, surf, m.k_A, m.k_B, m.B_inf, space=space, out_max=65535, prior=prior,
                              lam2=lam2, sigma=sigma, noise2=noise2, detail2=noise2[::-1] * 10)
            Jr, cr, nr = dewater_reference(img, r, surf, m, space=space, prior=prior, lam2=lam2, noise2=noise2,
                                           detail2=noise2[::-1] * 10)
            assert np.abs(J / 65535 - Jr).max() < 2e-5  # quantisation 7.6e-6 + float32 inputs
            assert np.abs(c - cr).max() < 1e-5 and n == nr
            assert 0 < c[surf].min() and c[surf].max() < 1 and c.std() > 0.05  # not a constant map
            if prior is None:
                continue
            # the channels together: a correlated covariance of what the model lacks, and a max_gain low enough
            # that some rows of the gain matrix are scaled down to the cap
            cov = np.array([[4e-3, 3e-3, 2e-3], [3e-3, 4e-3, 3.5e-3], [2e-3, 3.5e-3, 5e-3]])
            for g in (8.0, 2.5):
                J, c, n = dewater(img, r, surf, m.k_A, m.k_B, m.B_inf, max_gain=g, space=space, out_max=65535,
                                  prior=prior, lam2=lam2, sigma=sigma, noise2=noise2, detail_cov=cov)
                Jr, cr, nr = dewater_reference(img, r, surf, m, max_gain=g, space=space, prior=prior, lam2=lam2,
                                               noise2=noise2, detail_cov=cov)
                assert np.abs(J / 65535 - Jr).max() < 2e-5 and np.abs(c - cr).max() < 1e-5 and n == nr
            # the photo's local disagreement with the model: window means, and through the expected error
            for rad, step, row0, rows in ((1, 1, 0, None), (3, 1, 0, None), (5, 2, 3, (2, 11)), (6, 3, 7, (0, 13))):
                mis = local_misfit(img, r, surf, m.k_A, m.k_B, m.B_inf, prior, rad, space=space, step=step,
                                   row0=row0, out_rows=rows)
                mr = local_misfit_reference(img, r, surf, m, prior, rad, space=space, step=step, row0=row0,
                                            out_rows=rows)
                assert mis.shape == mr.shape and np.abs(mis - mr).max() < 1e-5 * max(1.0, mr.max())
            mr = local_misfit_reference(img, r, surf, m, prior, 2, space=space)
            J, c, n = dewater(img, r, surf, m.k_A, m.k_B, m.B_inf, space=space, out_max=65535, prior=prior,
                              lam2=lam2, sigma=sigma, noise2=noise2, detail_cov=cov, misfit=mr)
            Jr, cr2, nr = dewater_reference(img, r, surf, m, space=space, prior=prior, lam2=lam2, noise2=noise2,
                                            detail_cov=cov, misfit=mr)
            assert np.abs(J / 65535 - Jr).max() < 2e-5 and np.abs(c - cr2).max() < 1e-5 and n == nr
            _, c0, _ = dewater_reference(img, r, surf, m, space=space, prior=prior, lam2=lam2, noise2=noise2,
                                         detail_cov=cov)
            assert (cr2 <= c0 + 1e-12).all() and (cr2 < c0 - 1e-3).mean() > 0.3  # the misfit only lowers it


def test_calibration_sums_match_reference():
    """The calibration's fused kernel against the numpy code it replaced (both spaces, constant and per-pixel
    coefficients, strided rows, holes in the surface that break the horizontal pairs)."""
    from pipeline.restore._kernels import calibration_sums
    from pipeline.restore.dewater import _k
    from pipeline.restore.frame import calibration_sums_reference

    rng = np.random.default_rng(7)
    img = (rng.random((23, 31, 3)) * 255).astype(np.uint8)
    r = rng.uniform(0.1, 12, (23, 31)).astype(np.float32)
    surf = rng.random((23, 31)) > 0.25
    prior = rng.random((23, 31, 3)).astype(np.float32)
    B = np.array([0.1, 0.3, 0.35])
    for kA, kB in (([0.3, 0.1, 0.05], [0.2, 0.1, 0.1]),
                   (rng.random((23, 31, 3)).astype(np.float32), rng.random((23, 31, 3)).astype(np.float32))):
        for space in ("srgb", "linear"):
            for st in (1, 3):
                got = calibration_sums(img, 1 / 255, r, surf, _k(kA), _k(kB), B, space == "linear", prior, st)
                ref = calibration_sums_reference(img / 255, r, surf, np.asarray(kA, np.float32),
                                                 np.asarray(kB, np.float32), B, prior, st, space)
                assert got[3] == ref[3] > 100 and got[4] == ref[4] > 50
                for a, b in zip(got[:3], ref[:3]):
                    assert np.abs(a - b).max() < 1e-9 * max(1.0, np.abs(b).max())
                assert np.abs(got[1]).max() > 1e-3  # the lag products are not all zero


def test_dewater_reads_a_nan_misfit_as_zero():
    """The kernel reads NaN in the misfit as 0 (it replaced a full-frame nan_to_num); +inf caps the error at 1."""
    rng = np.random.default_rng(8)
    img = rng.random((9, 11, 3)).astype(np.float32)
    r = rng.uniform(0.5, 8, (9, 11)).astype(np.float32)
    surf = np.ones((9, 11), bool)
    prior = rng.random((9, 11, 3)).astype(np.float32)
    mis = rng.uniform(0, 0.02, (9, 11, 3)).astype(np.float32)
    kw = dict(prior=prior, lam2=np.array([0.05, 0.1, 0.2]), noise2=np.full(3, 1e-4), detail2=np.full(3, 1e-3))
    B, kA, kB = np.array([0.1, 0.2, 0.3]), np.array([0.3, 0.1, 0.05]), np.array([0.2, 0.1, 0.1])
    bad, zero = mis.copy(), mis.copy()
    bad[2, 3, 1], zero[2, 3, 1] = np.nan, 0.0
    _, c_bad, _ = dewater(img, r, surf, kA, kB, B, misfit=bad, **kw)
    _, c_zero, _ = dewater(img, r, surf, kA, kB, B, misfit=zero, **kw)
    _, c_mis, _ = dewater(img, r, surf, kA, kB, B, misfit=mis, **kw)
    assert np.isfinite(c_bad).all() and (c_bad == c_zero).all() and c_mis[2, 3] < c_zero[2, 3]
    bad[2, 3, 1] = np.inf
    _, c_inf, _ = dewater(img, r, surf, kA, kB, B, misfit=bad, **kw)
    others = np.arange(99) != 2 * 11 + 3
    assert 0 < c_inf[2, 3] < 0.1 and (c_inf.ravel()[others] == c_mis.ravel()[others]).all()


def test_surface_range_matches_reference():
    from pipeline.restore._kernels import surface_range
    from pipeline.restore.frame import surface_range_reference

    rng = np.random.default_rng(9)
    z = rng.uniform(-1, 5, (17, 23)).astype(np.float32)
    z[3, 4] = np.nan
    xn, yn = (rng.uniform(-0.7, 0.7, (17, 23)).astype(np.float32) for _ in range(2))
    inside = rng.random((17, 23)) > 0.1
    vals = rng.random((17, 23, 6)).astype(np.float32)
    got, ref = surface_range(z, xn, yn, inside, vals), surface_range_reference(z, xn, yn, inside, vals)
    assert got[1].any() and (~got[1]).any() and (got[2] > 0).any()
    for a, b in zip(got, ref):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)  # the same float32 arithmetic, NaN where numpy has it
