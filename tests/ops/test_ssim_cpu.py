"""The numba SSIM operator (``pipeline.ops.ssim_cpu``) against its torch twin ``image_losses.ssim_map``: value
and gradient, at image sizes down to smaller than the window, on black and saturated images; finite differences
in float64; the same bits on every call; one graph under ``torch.compile`` (no break around the operator)."""

from __future__ import annotations

import pytest
import torch

from pipeline.ops.image_losses import _C1, _C2, gaussian_window_1d, photometric_losses, ssim, ssim_map
from pipeline.ops.ssim_cpu import ssim_planes


def _twin(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ssim_map(a, b).mean()


def _value_and_grad(fn, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    a = a.detach().clone().requires_grad_(True)
    v = fn(a, b)
    (g,) = torch.autograd.grad(v, a)
    return v.detach(), g


@pytest.mark.parametrize("shape", [(240, 320, 3), (2, 31, 17, 3), (4, 6, 3), (1, 1, 3), (3, 40, 9, 1)])
def test_matches_the_torch_twin(shape):
    """Value within 2e-6 absolute, gradient within 1e-5 of its largest entry (float32 sums in another order)."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(*shape, generator=g), torch.rand(*shape, generator=g)
    b = 0.7 * a + 0.3 * b  # correlated, as a render and its photo are
    v, grad = _value_and_grad(ssim, a, b)
    v_ref, grad_ref = _value_and_grad(_twin, a, b)
    assert abs(float(v) - float(v_ref)) < 2e-6
    assert float((grad - grad_ref).abs().max()) <= 1e-5 * float(grad_ref.abs().max())


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_black_and_saturated_images_stay_finite(fill):
    """A constant render (black or saturated) against a textured photo: finite, and as the twin. Against itself:
    SSIM 1 and a gradient that is float noise (≤ 1e-7, the zero padding's cancellation at the borders; a
    gradient entry of a 48x64 image is ~1/9216 in scale)."""
    g = torch.Generator().manual_seed(1)
    flat, photo = torch.full((48, 64, 3), fill), torch.rand(48, 64, 3, generator=g)
    v, grad = _value_and_grad(ssim, flat, photo)
    v_ref, grad_ref = _value_and_grad(_twin, flat, photo)
    assert torch.isfinite(v) and torch.isfinite(grad).all()
    assert abs(float(v) - float(v_ref)) < 2e-6
    assert float((grad - grad_ref).abs().max()) <= 1e-5 * float(grad_ref.abs().max())
    v, grad = _value_and_grad(ssim, flat, flat)
    assert float(v) == pytest.approx(1.0, abs=1e-6) and float(grad.abs().max()) <= 1e-7


def test_gradient_against_finite_differences():
    """float64 planes through the operator: torch.autograd.gradcheck (central differences)."""
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2, 9, 14, dtype=torch.float64, generator=g).requires_grad_(True)
    y = torch.rand(2, 9, 14, dtype=torch.float64, generator=g)
    g = gaussian_window_1d(like=x)
    assert torch.autograd.gradcheck(lambda t: ssim_planes(t, y, g, _C1, _C2), (x,))


def test_same_bits_every_call():
    """Row-parallel with one writer per row: the schedule cannot change a bit of the value or the gradient."""
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(120, 160, 3, generator=g), torch.rand(120, 160, 3, generator=g)
    v0, g0 = _value_and_grad(ssim, a, b)
    for _ in range(3):
        v, grad = _value_and_grad(ssim, a, b)
        assert torch.equal(v, v0) and torch.equal(grad, g0)


def test_a_target_that_needs_a_gradient_goes_to_the_twin():
    """The operator differentiates the render only; a second image that needs a gradient gets one (the twin)."""
    g = torch.Generator().manual_seed(4)
    a = torch.rand(20, 30, 3, generator=g, requires_grad=True)
    b = torch.rand(20, 30, 3, generator=g, requires_grad=True)
    ssim(a, b).backward()
    assert b.grad is not None and float(b.grad.abs().max()) > 0


def test_bad_planes_are_refused():
    x, g = torch.rand(3, 8, 8), gaussian_window_1d(like=torch.rand(1))
    with pytest.raises(ValueError, match="P, H, W"):
        ssim_planes(x, torch.rand(3, 8, 9), g, _C1, _C2)
    with pytest.raises(ValueError, match="odd window"):
        ssim_planes(x, x, g[:10], _C1, _C2)
    with pytest.raises(ValueError, match="odd window"):
        ssim_planes(x, x, g.double(), _C1, _C2)


def test_one_graph_under_torch_compile():
    """The loss that calls the operator traces into a single graph (a custom operator, not a break)."""
    g = torch.Generator().manual_seed(5)
    r = torch.rand(1, 3, 24, 32, generator=g, requires_grad=True)
    t = torch.rand(1, 3, 24, 32, generator=g)
    explained = torch._dynamo.explain(lambda r, t: sum(photometric_losses(r, t, 0.2, channels_first=True).values()))(
        r, t)
    assert explained.graph_break_count == 0 and explained.graph_count == 1


def test_warmup_compiles_both_kernels():
    """``dualphys warmup``'s call: both kernels have a compiled signature for float32 planes afterwards."""
    from pipeline.ops import _ssim_kernels
    from pipeline.ops.ssim_cpu import compile_ssim_kernels

    assert compile_ssim_kernels() >= 0.0
    assert _ssim_kernels.ssim_fwd.signatures and _ssim_kernels.ssim_bwd.signatures
