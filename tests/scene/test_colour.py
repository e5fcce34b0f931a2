import numpy as np
import pytest
import torch

from pipeline.scene.colour import linear_to_srgb, srgb_to_linear


def test_known_values():
    # IEC 61966-2-1: 0.5 encoded is 0.21404 linear; 0.04045 sits on both segments (0.0031308); 1 maps to 1
    assert float(srgb_to_linear(0.5)) == pytest.approx(0.214041, abs=1e-6)
    assert float(srgb_to_linear(0.04045)) == pytest.approx(0.0031308, abs=1e-7)
    assert float(srgb_to_linear(1.0)) == pytest.approx(1.0, abs=1e-12)
    assert float(linear_to_srgb(0.18)) == pytest.approx(0.461356, abs=1e-6)  # mid grey
    assert float(linear_to_srgb(0.0)) == 0.0
    assert float(srgb_to_linear(np.float64(128 / 255))) == pytest.approx(0.215861, abs=1e-6)


def test_round_trip_numpy_and_torch_agree():
    x = np.linspace(0.0, 1.0, 10001)
    assert np.max(np.abs(linear_to_srgb(srgb_to_linear(x)) - x)) < 1e-12
    assert np.max(np.abs(srgb_to_linear(linear_to_srgb(x)) - x)) < 1e-12
    t = torch.as_tensor(x)
    lin_t = srgb_to_linear(t)
    assert isinstance(lin_t, torch.Tensor) and lin_t.dtype == torch.float64
    assert np.max(np.abs(lin_t.numpy() - srgb_to_linear(x))) < 1e-15  # libm vs torch pow: last ulp
    assert np.max(np.abs(linear_to_srgb(lin_t).numpy() - x)) < 1e-12
    # continuous at the segment joint (the standard's constants meet to ~1e-8) and monotonic
    assert abs(srgb_to_linear(0.04045 + 1e-12) - srgb_to_linear(0.04045)) < 1e-7
    assert np.all(np.diff(srgb_to_linear(x)) > 0)


def test_negative_values_follow_the_linear_segment_without_nan():
    x = np.array([-0.1, -1e-3])
    assert np.allclose(srgb_to_linear(x), x / 12.92)
    assert np.allclose(linear_to_srgb(x), x * 12.92)
    assert not torch.isnan(srgb_to_linear(torch.tensor([-0.5, 0.3]))).any()
