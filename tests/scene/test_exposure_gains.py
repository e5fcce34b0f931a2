"""A photo's exposure as gains on linear light (pipeline.scene.exposure): neutral undoes exposed, in both spaces,
the same on numpy and torch, and differentiable in the gains."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.exposure import exposed, mean_neutral, neutral


@pytest.mark.parametrize("space", ["srgb", "linear"])
def test_neutral_undoes_exposed(space):
    x = np.random.default_rng(0).uniform(0, 0.7, (5, 7, 3))
    lg = np.log([1.3, 0.8, 1.05])
    np.testing.assert_allclose(neutral(exposed(x, lg, space), lg, space), x, atol=1e-12)


def test_a_gain_multiplies_linear_light():
    x = np.array([[0.2, 0.5, 0.8]])
    lg = np.log([1.2, 0.7, 1.0])
    np.testing.assert_allclose(srgb_to_linear(exposed(x, lg, "srgb")), srgb_to_linear(x) * np.exp(lg), rtol=1e-12)


def test_torch_matches_numpy_and_has_a_gradient():
    x = np.random.default_rng(1).uniform(0, 1, (4, 4, 3)).astype(np.float32)
    lg = torch.tensor([0.2, -0.1, 0.05], requires_grad=True)
    got = neutral(torch.from_numpy(x), lg, "srgb")
    np.testing.assert_allclose(got.detach().numpy(), neutral(x, lg.detach().numpy(), "srgb"), atol=1e-6)
    got.sum().backward()
    assert lg.grad is not None and (lg.grad < 0).all()  # a larger gain means a darker neutral photo


def test_mean_neutral_and_bad_space():
    lg = mean_neutral(np.log([[1.2, 1, 1], [0.9, 1.1, 1], [1, 1, 0.5]]))
    np.testing.assert_allclose(lg.mean(0), 0, atol=1e-15)
    with pytest.raises(ValueError, match="colour space"):
        neutral(np.zeros(3), np.zeros(3), "xyz")
