"""Metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.ops.metrics import (
    coefficient_error,
    mean_ssim,
    per_metre,
    pooled_mse,
    pooled_psnr,
    psnr,
    scale_aligned_depth_error,
)


def test_pooled_psnr_pools_pixels_not_views() -> None:
    a = np.zeros((2, 2, 3))
    b = np.full((2, 2, 3), 0.1)  # mse 0.01
    c = np.zeros((4, 4, 3))  # perfect, 4x the pixels
    assert pooled_mse([(a, b)]) == pytest.approx(0.01)
    assert pooled_psnr([(a, b)]) == pytest.approx(20.0)
    # pooled: 0.01 * 12 / (12 + 48) = 0.002 → 26.99 dB; a per-view mean of PSNRs would be inf.
    assert pooled_psnr([(a, b), (c, c)]) == pytest.approx(-10 * math.log10(0.002))
    assert psnr(0.0) == math.inf
    with pytest.raises(ValueError):
        pooled_mse([(a, c)])


def test_pooled_psnr_of_tensors_pools_like_arrays() -> None:
    """Training's held-out curve passes torch tensors: summed by torch in float64, pooled the same way."""
    a, b = torch.zeros(4, 4, 3), torch.zeros(4, 4, 3)
    c = torch.full((4, 4, 3), 0.1)  # mse 0.01 for the second pair, 0 for the first: pooled mse 0.005
    assert pooled_psnr([(a, b), (a, c)]) == pytest.approx(-10 * math.log10(0.005))
    assert pooled_psnr([(a, b)]) == math.inf
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(30, 40, 3, generator=g), torch.rand(30, 40, 3, generator=g)
    assert pooled_psnr([(x, y)]) == -10 * math.log10(float((x.double() - y.double()).square().sum()) / x.numel())
    assert pooled_psnr([(x, y)]) == pytest.approx(pooled_psnr([(x.numpy(), y.numpy())]), abs=1e-9)
    keep = np.zeros((30, 40), bool)
    keep[:10] = True
    assert pooled_psnr([(x, y)], [keep]) == pytest.approx(pooled_psnr([(x[:10], y[:10])]), abs=1e-9)


def test_masked_pooled_psnr_scores_only_the_kept_pixels() -> None:
    a = np.zeros((2, 2, 3))
    b = np.zeros((2, 2, 3))
    b[0, 0] = 0.5  # one bad pixel
    keep = np.ones((2, 2), bool)
    keep[0, 0] = False
    assert pooled_psnr([(a, b)], [keep]) == math.inf  # the bad pixel is left out
    only_bad = ~keep
    assert pooled_mse([(a, b)], [only_bad]) == pytest.approx(0.25)
    # two views: 1 kept pixel (error 0.25) + 4 kept perfect pixels → 0.25 * 3 / 15
    assert pooled_mse([(a, b), (a, a)], [only_bad, np.ones((2, 2), bool)]) == pytest.approx(0.05)
    assert math.isnan(pooled_psnr([(a, b)], [np.zeros((2, 2), bool)]))  # nothing kept: NaN, not a score
    with pytest.raises(ValueError, match="does not fit"):
        pooled_mse([(a, b)], [np.ones((3, 2), bool)])
    with pytest.raises(ValueError, match="masks for"):
        pooled_mse([(a, b)], [])


def test_ssim_identity_and_degradation() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((32, 32, 3)).astype(np.float32)
    assert mean_ssim([(img, img)]) == pytest.approx(1.0, abs=1e-5)
    smooth = np.broadcast_to(np.linspace(0.2, 0.8, 32)[None, :, None], (32, 32, 3)).astype(np.float32)
    noisy = np.clip(smooth + rng.normal(0, 0.1, smooth.shape), 0, 1).astype(np.float32)
    # Luminance and contrast terms match; the structure term for noise of std 0.1 on a flat-ish ramp is low.
    assert mean_ssim([(noisy, smooth)]) < 0.5


def test_depth_error_is_scale_free() -> None:
    gt = np.linspace(1, 5, 100).reshape(10, 10)
    out = scale_aligned_depth_error([gt / 3.7], [gt])
    assert out["scale"] == pytest.approx(3.7) and out["abs_error"] < 1e-12
    noisy = scale_aligned_depth_error([gt * (1 + 0.1 * np.sign(np.sin(np.arange(100)))).reshape(10, 10)], [gt])
    assert 0.05 < noisy["rel_error"] < 0.15


def test_coefficient_error() -> None:
    e = coefficient_error([0.5, 0.2, 0.1], [0.55, 0.17, 0.11])
    assert e["abs_error"] == pytest.approx([0.05, 0.03, 0.01])
    assert e["rel_error"][0] == pytest.approx(0.05 / 0.55)


def test_per_metre_divides_by_the_metres_per_scene_unit() -> None:
    # one scene unit is 2 m: a coefficient of 0.5 per unit is 0.25 per metre
    assert per_metre([0.5, 0.2, 0.1], 2.0) == pytest.approx([0.25, 0.1, 0.05])
    assert per_metre((), 3.0) == []
