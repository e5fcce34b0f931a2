"""The dewatering rules: gain cap, no-surface pixels, finite outputs at extremes, medium coefficients."""

import numpy as np

from pipeline.restore.dewater import dewater
from pipeline.restore.medium import coefficients_from_maps


def _gain(J, img, surf):
    return J.astype(np.float64) / 65535 / np.maximum(img, 1e-9)


def test_gain_cap_holds_per_channel():
    img = np.full((4, 50, 3), 0.1, np.float32)
    r = np.tile(np.linspace(0, 100, 50, dtype=np.float32), (4, 1))
    surf = np.ones((4, 50), bool)
    for g in (2.0, 8.0, 30.0):
        J, c, _ = dewater(img, r, surf, np.array([0.5, 0.2, 0.1]), np.zeros(3), np.zeros(3), max_gain=g,
                          out_max=65535)
        assert _gain(J, img, surf).max() <= g * (1 + 1e-4)
        assert c[:, -1].max() < 0.011 and c[:, 0].min() == 1  # at the cap: an expected error ≥ 1; no water: 1
        assert (np.diff(c[0]) <= 1e-7).all()  # confidence falls with range


def test_with_the_models_prior_the_gain_never_exceeds_the_cap_and_far_pixels_lean_on_the_model():
    """J = (A(I − B) + λ²J_m) / (A² + λ²), λ = 1/(2 max_gain): dJ/dI ≤ max_gain at every range; near, the photo's
    own (I − B)/A; far, the model's J_m. The confidence is 1 with no water between and falls with range."""
    W = 200
    r = np.tile(np.linspace(0, 60, W, dtype=np.float32), (2, 1))
    surf = np.ones((2, W), bool)
    kA, kB, binf = np.array([0.5, 0.2, 0.1]), np.array([0.3, 0.2, 0.1]), np.array([0.05, 0.2, 0.3])
    prior = np.full((2, W, 3), 0.4, np.float32)
    for g in (2.0, 8.0, 30.0):
        lo, hi = np.full((2, W, 3), 0.30, np.float32), np.full((2, W, 3), 0.31, np.float32)
        J0, c, _ = dewater(lo, r, surf, kA, kB, binf, max_gain=g, out_max=65535, prior=prior)
        J1, _, _ = dewater(hi, r, surf, kA, kB, binf, max_gain=g, out_max=65535, prior=prior)
        gain = (J1.astype(np.float64) - J0) / 65535 / 0.01
        assert gain.max() <= g * (1 + 1e-3) and gain.max() > 0.9 * g  # the cap is reached, never passed
        assert c[0, 0] == 1 and c[0, -1] < 0.02 and (np.diff(c[0]) <= 1e-7).all()
    A_far = np.exp(-kA * 60)
    assert np.allclose(J0[0, -1] / 65535, 0.4, atol=2e-3 + A_far.max())  # far: the model's value
    B0 = binf * -np.expm1(-kB * float(r[0, 1]))
    near = (0.30 - B0) / np.exp(-kA * float(r[0, 1]))
    assert np.allclose(J0[0, 1] / 65535, near, atol=2e-3)  # near: the photo's own (I − B)/A


def test_channels_restored_together_keep_every_gain_under_the_cap():
    """With a covariance across channels each output channel also moves with the other channels' photo values;
    the gains of a row together, Σ_k |dJ_c/dI_k|, stay ≤ max_gain at every range. A diagonal covariance is the
    per-channel rule exactly."""
    W = 200
    r = np.tile(np.linspace(0, 60, W, dtype=np.float32), (2, 1))
    surf = np.ones((2, W), bool)
    kA, kB, binf = np.array([0.5, 0.2, 0.1]), np.array([0.3, 0.2, 0.1]), np.array([0.05, 0.2, 0.3])
    prior = np.full((2, W, 3), 0.4, np.float32)
    cov = np.array([[9.0, 2.5, 2.0], [2.5, 1.0, 0.9], [2.0, 0.9, 1.0]]) * 1e-3  # red lacks the most, ρ ≈ 0.8
    base = np.full((2, W, 3), 0.30, np.float32)
    for g in (2.0, 8.0, 30.0):
        J0, _, _ = dewater(base, r, surf, kA, kB, binf, max_gain=g, out_max=65535, prior=prior, detail_cov=cov)
        gains = np.zeros((W, 3, 3))
        for k in range(3):
            up = base.copy()
            up[..., k] += 0.01
            J1, _, _ = dewater(up, r, surf, kA, kB, binf, max_gain=g, out_max=65535, prior=prior, detail_cov=cov)
            gains[:, :, k] = (J1[0].astype(np.float64) - J0[0]) / 65535 / 0.01
        total = np.abs(gains).sum(-1)
        assert total.max() <= g * (1 + 2e-3) and total.max() > 0.9 * g, (g, total.max())
        assert np.abs(gains[:, 0, 1:]).max() > 0.1  # red does move with green and blue
    diag = np.diag(np.diag(cov))
    for lam2 in (None, np.array([0.01, 0.05, 0.2])):
        a = dewater(base, r, surf, kA, kB, binf, out_max=65535, prior=prior, lam2=lam2, detail_cov=diag)
        b = dewater(base, r, surf, kA, kB, binf, out_max=65535, prior=prior, lam2=lam2, detail2=np.diag(cov))
        assert np.abs(a[0].astype(int) - b[0]).max() <= 1 and np.abs(a[1] - b[1]).max() < 1e-6


def test_confidence_is_the_expected_error_of_the_water_and_the_noise():
    """c = τ²/(τ² + mean e²): 1 for a known water and a noiseless photo; lower everywhere as the water's σ or
    the photo's noise grows; 1/2 where the expected error is τ (one channel's β_D known to a log-σ s: e = J·k·r·s)."""
    W = 60
    r = np.tile(np.linspace(0.5, 8, W, dtype=np.float32), (2, 1))
    surf = np.ones((2, W), bool)
    img = np.full((2, W, 3), 0.3, np.float32)
    kA, kB, binf = np.array([0.4, 0.15, 0.1]), np.array([0.3, 0.15, 0.1]), np.array([0.1, 0.25, 0.3])
    conf = {}
    cases = (("known", np.zeros((3, 3)), None), ("measured", np.full((3, 3), 0.1), None),
             ("loose", np.full((3, 3), 0.3), None), ("noisy", np.full((3, 3), 0.1), np.full(3, 1e-3)))
    for name, sigma, noise2 in cases:
        _, conf[name], _ = dewater(img, r, surf, kA, kB, binf, max_gain=50.0, sigma=sigma, noise2=noise2)
    assert (conf["known"] == 1).all()
    assert (conf["loose"] < conf["measured"]).all() and (conf["noisy"] < conf["measured"]).all()
    assert (np.diff(conf["measured"][0]) < 0).all()  # falls with range
    # one uncertain coefficient: β_D of red; e = J·k·r·s with J the restored red, the other channels exact
    sigma = np.zeros((3, 3))
    sigma[0, 0] = 0.2
    J, c, _ = dewater(img, r, surf, kA, kB, binf, max_gain=50.0, sigma=sigma, out_max=65535)
    e = J[..., 0] / 65535 * kA[0] * r * 0.2
    assert np.allclose(c, 0.01 / (0.01 + np.minimum(e, 1) ** 2 / 3), atol=2e-4)


def test_no_surface_is_the_photo_with_zero_confidence():
    rng = np.random.default_rng(0)
    img = (rng.random((6, 7, 3)) * 255).astype(np.uint8)
    surf = np.zeros((6, 7), bool)
    J, c, n = dewater(img, np.full((6, 7), 5.0), surf, np.ones(3), np.ones(3), np.full(3, 0.3))
    assert (J == img).all() and (c == 0).all() and n == 0


def test_finite_at_extremes():
    H, W = 4, 6
    for val in (0.0, 1.0):
        img = np.full((H, W, 3), val, np.float32)
        for depth in (0.0, 1e4, np.nan, -3.0):
            for k in (0.0, 1e-9, 50.0, 1e6, np.nan):
                J, c, _ = dewater(img, np.full((H, W), depth, np.float32), np.ones((H, W), bool), np.full(3, k),
                                  np.full(3, k), np.array([0.0, 0.5, 1.0]), space="linear")
                assert J.dtype == np.uint8 and np.isfinite(c).all() and (c >= 0).all() and (c <= 1).all()


def test_coefficients_from_rendered_maps_roundtrip():
    rng = np.random.default_rng(1)
    r = rng.uniform(0.5, 12, (20, 30))
    kA, kB, binf = np.array([0.4, 0.15, 0.1]), np.array([0.3, 0.2, 0.1]), np.array([0.05, 0.2, 0.3])
    A = np.exp(-kA * r[..., None])
    B = binf * (1 - np.exp(-kB * r[..., None]))
    alpha = np.ones((20, 30))
    alpha[:5] = 0.0
    r[5, :] = 0.0  # no range: not identifiable, filled
    m = coefficients_from_maps(A, B, r, binf, alpha)
    assert np.abs(m.k_A[6:] - kA).max() < 1e-5 and np.abs(m.k_B[6:] - kB).max() < 1e-5
    assert np.abs(m.k_A - kA).max() < 1e-5  # filled pixels take their neighbours' (here equal) values
    sat = coefficients_from_maps(np.zeros((3, 3, 3)), np.ones((3, 3, 3)), np.ones((3, 3)), binf)
    assert np.isfinite(sat.k_A).all() and np.isfinite(sat.k_B).all() and (sat.k_A >= 0).all()


def test_prior_weights_separate_the_photos_noise_from_what_the_model_lacks():
    """e = A·d + n with d smooth (what the model lacks) and n white (the photo's noise): the lag-1 products keep
    A²σ_d² and drop σ_n², so λ² = σ_n² / σ_d² comes back; never below the cap's floor."""
    from pipeline.restore.dewater import prior_weights

    rng = np.random.default_rng(4)
    H, W = 400, 600
    k = np.exp(-0.5 * (np.arange(-8, 9) / 3.0) ** 2)
    d = np.apply_along_axis(lambda r: np.convolve(r, k / np.sqrt((k ** 2).sum()), "same"), 1,
                            rng.normal(0, 1, (H, W)))  # unit variance, strongly correlated along rows
    sd, sn, A = np.array([0.02, 0.05, 0.1]), np.array([0.01, 0.01, 0.01]), np.array([0.8, 0.5, 0.3])
    e = A * sd * d[..., None] + sn * rng.normal(0, 1, (H, W, 3))
    lam2 = prior_weights((e ** 2).mean((0, 1)), (e[:, :-1] * e[:, 1:]).mean((0, 1)), A ** 2, max_gain=8.0)
    # within 30 %: detail that is not perfectly smooth (lag-1 correlation 0.97 here) counts partly as noise
    assert np.allclose(lam2, (sn / sd) ** 2, rtol=0.3), (lam2, (sn / sd) ** 2)
    assert (prior_weights(np.full(3, 1e-6), np.full(3, 1e-6), np.ones(3), 8.0) == (0.5 / 8) ** 2).all()


def test_the_waters_uncertainty_comes_from_the_fit_and_falls_back_on_the_prior():
    """``water_sigma`` reads train.json's fit; a coefficient it could not determine (None) and a job without a fit
    take the water type's prior width, which gives a lower confidence than a measured water."""
    from pipeline.restore.dewater import UNMEASURED_SIGMA, _sigma
    from pipeline.restore.medium import water_sigma

    unc = {"beta_D": {"sigma": [0.1, 0.1, 0.1]}, "beta_B": {"sigma": [0.2, None, 0.2]}, "B_inf": {"sigma": [0.05] * 3}}
    s = water_sigma({"medium": {"estimate": {"uncertainty": unc}}})
    assert s.shape == (3, 3) and s[0, 0] == 0.1 and np.isnan(s[1, 1])
    assert _sigma(s)[1, 1] == UNMEASURED_SIGMA[1, 1] and _sigma(s)[2, 2] == 0.05
    assert water_sigma({"medium": None}) is None and water_sigma(None) is None
    r = np.full((1, 5), 3.0, np.float32)
    args = (np.full((1, 5, 3), 0.3, np.float32), r, np.ones((1, 5), bool), np.array([0.3, 0.1, 0.1]),
            np.array([0.2, 0.1, 0.1]), np.array([0.1, 0.2, 0.3]))
    measured = dewater(*args, sigma=s)[1]
    unmeasured = dewater(*args, sigma=None)[1]
    assert (unmeasured < measured).all()
