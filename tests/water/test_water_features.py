"""Water-classifier features: values checked by hand on tiny arrays."""

from __future__ import annotations

import math

import pytest
import torch

from pipeline.water.features import (
    EPS,
    FEATURE_NAMES,
    NUM_FEATURES,
    blue_green_ratio,
    dark_channel,
    image_features,
    resize_short_side,
    saturation,
    veil_colour,
)


def _const(r: float, g: float, b: float, h: int = 4, w: int = 6) -> torch.Tensor:
    return torch.tensor([r, g, b]).reshape(1, 3, 1, 1).expand(1, 3, h, w).contiguous()  # [1, 3, h, w]


def _feat(x: torch.Tensor) -> dict[str, float]:
    f = image_features(x, resize=False)
    assert f.shape == (x.shape[0], NUM_FEATURES)
    return dict(zip(FEATURE_NAMES, f[0].tolist()))


def test_pure_blue_image():
    f = _feat(_const(0.0, 0.0, 0.8))
    assert f["log_bg_ratio"] == pytest.approx(math.log((0.8 + EPS) / EPS), rel=1e-6)
    assert f["log_rg_ratio"] == pytest.approx(0.0, abs=1e-6)
    assert f["mean_b"] == pytest.approx(0.8) and f["mean_r"] == 0.0 and f["std_b"] == pytest.approx(0.0, abs=1e-7)
    assert f["dark_channel_mean"] == 0.0
    assert f["bright_channel_mean"] == pytest.approx(0.8)
    assert f["saturation_mean"] == pytest.approx(1.0) and f["saturation_std"] == pytest.approx(0.0, abs=1e-7)
    assert f["luma_q50"] == pytest.approx(0.114 * 0.8, rel=1e-5)
    assert f["rms_contrast"] == pytest.approx(0.0, abs=1e-5) and f["gradient_contrast"] == pytest.approx(0.0, abs=1e-6)


def test_uniform_grey_and_tinted_values():
    f = _feat(_const(0.5, 0.5, 0.5))
    assert f["log_bg_ratio"] == pytest.approx(0.0, abs=1e-7) and f["saturation_mean"] == pytest.approx(0.0, abs=1e-7)
    assert f["dark_channel_mean"] == pytest.approx(0.5) and f["veil_log_bg"] == pytest.approx(0.0, abs=1e-7)
    # Blue-green water colour: b/g = 0.4 / 0.3, dark channel = min channel = 0.1, HSV saturation (0.4-0.1)/0.4.
    f = _feat(_const(0.1, 0.3, 0.4))
    assert math.exp(f["log_bg_ratio"]) == pytest.approx((0.4 + EPS) / (0.3 + EPS), rel=1e-6)
    assert f["dark_channel_mean"] == pytest.approx(0.1)
    assert f["saturation_mean"] == pytest.approx(0.75)
    assert f["q05_g"] == pytest.approx(0.3) and f["q95_r"] == pytest.approx(0.1)
    assert f["cv_g"] == pytest.approx(0.0, abs=1e-6)


def test_contrast_of_a_half_black_half_white_image():
    x = torch.zeros(1, 3, 4, 4)
    x[..., 2:] = 1.0  # right half white
    f = _feat(x)
    assert f["rms_contrast"] == pytest.approx(0.5 / (0.5 + EPS), rel=1e-5)  # std(Y) / (mean(Y) + eps)
    # Forward differences on the 3×3 crop: one column of 3 pixels has |∇Y| = 1, mean 1/3, divided by mean Y 0.5.
    assert f["gradient_contrast"] == pytest.approx((1 / 3) / (0.5 + EPS), rel=1e-6)
    assert f["luma_q05"] == pytest.approx(0.0, abs=1e-6) and f["luma_q95"] == pytest.approx(1.0, rel=1e-6)


def test_dark_channel_min_filter_and_veil_colour():
    x = _const(0.5, 0.6, 0.7, h=5, w=5).clone()
    x[0, 0, 2, 2] = 0.0  # one black red pixel: the 3×3 min filter spreads it over the centre 3×3 block
    d = dark_channel(x)[0]
    assert d.shape == (5, 5)
    assert (d[1:4, 1:4] == 0).all() and float(d[0, 0]) == pytest.approx(0.5)
    assert veil_colour(x)[0].tolist() == pytest.approx([0.5, 0.6, 0.7])  # from the haziest 10 %, not the hole


def test_ratio_and_saturation_helpers():
    x = torch.cat([_const(0.0, 0.25, 0.5), _const(0.0, 0.0, 0.0)])  # [2, 3, 4, 6]
    assert blue_green_ratio(x).tolist() == pytest.approx([(0.5 + EPS) / (0.25 + EPS), 1.0])
    assert saturation(x)[1].abs().max() == 0  # black is defined as unsaturated, not NaN


def test_resize_keeps_aspect_and_means():
    x = torch.rand(2, 3, 96, 128, generator=torch.Generator().manual_seed(0))
    y = resize_short_side(x, 48)
    assert y.shape == (2, 3, 48, 64)
    assert torch.allclose(y.mean(dim=(2, 3)), x.mean(dim=(2, 3)), atol=1e-6)  # area resampling keeps the mean


def test_features_are_scale_free_in_resolution():
    # The same smooth image at 64×48 and 256×192 gives nearly the same features after the internal resize.
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 192), torch.linspace(0, 1, 256), indexing="ij")
    big = torch.stack([0.2 + 0.1 * xx, 0.5 * yy + 0.2, 0.6 - 0.2 * xx * yy])[None]  # [1, 3, 192, 256]
    small = torch.nn.functional.interpolate(big, size=(48, 64), mode="area")
    assert torch.allclose(image_features(big), image_features(small), atol=1e-4)


def test_shape_errors():
    with pytest.raises(ValueError, match=r"\[N, 3, H, W\]"):
        image_features(torch.zeros(3, 4, 4))
