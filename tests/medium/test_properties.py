"""Numerical stability: finite forward and backward over extreme depths, coefficients and images."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.medium.attenuation import rgb_guided_attenuation
from pipeline.medium.formation import classical_formation
from pipeline.medium.losses import LossWeights, total_loss
from pipeline.medium.model import Medium
from pipeline.medium.scattering import depth_confidence, depth_edge_factor, multiscale_backscatter

sizes = st.sampled_from([(8, 8), (7, 5), (9, 13), (1, 1), (2, 3), (16, 11)])
images = st.sampled_from(["zeros", "ones", "random", "black_and_saturated"])


def _image(kind: str, h: int, w: int, g: torch.Generator) -> torch.Tensor:
    if kind == "zeros":
        return torch.zeros(1, 3, h, w)
    if kind == "ones":
        return torch.ones(1, 3, h, w)
    if kind == "random":
        return torch.rand(1, 3, h, w, generator=g)
    return (torch.rand(1, 3, h, w, generator=g) > 0.5).float()


@settings(max_examples=60, deadline=None)
@given(size=sizes, kind=images, d_max=st.floats(0.0, 1e4), beta=st.floats(0.0, 50.0), seed=st.integers(0, 99))
def test_formation_functions_are_finite(size, kind, d_max, beta, seed):
    g = torch.Generator().manual_seed(seed)
    h, w = size
    J = _image(kind, h, w, g).requires_grad_()
    D = (torch.rand(1, 1, h, w, generator=g) * d_max).requires_grad_()
    b = torch.full((3,), beta, requires_grad=True)
    outs = [
        classical_formation(J, D, b, b, torch.tensor([0.1, 0.5, 0.9])),
        rgb_guided_attenuation(D, torch.ones(3), b, torch.rand(1, 1, h, w, generator=g), 0.5, 1.2),
        multiscale_backscatter(D, b, torch.tensor([0.1, 0.5, 0.9]), depth_confidence(D), depth_edge_factor(D),
                               torch.rand(1, 1, h, w, generator=g), 0.5, 0.5),
    ]
    total = sum(o.sum() for o in outs)
    assert all(torch.isfinite(o).all() for o in outs)
    total.backward()
    for t in (J, D, b):
        assert torch.isfinite(t.grad).all()


@settings(max_examples=40, deadline=None)
@given(size=sizes, kind=images, d_max=st.floats(0.0, 1e4), beta=st.floats(0.0, 50.0), seed=st.integers(0, 99))
def test_full_model_and_losses_are_finite(size, kind, d_max, beta, seed):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    h, w = size
    m = Medium("dualphys", depth_scale=max(d_max, 1e-3) / 2 + 1e-3)
    with torch.no_grad():
        m.beta_d_raw.fill_(beta)  # softplus(beta) ≈ beta for large values; 0 → 0.69
        m.beta_b_raw.fill_(beta)
    J = _image(kind, h, w, g).requires_grad_()
    D = (torch.rand(1, 1, h, w, generator=g) * d_max).requires_grad_()
    alpha = torch.rand(1, 1, h, w, generator=g)
    target = _image(kind, h, w, g)
    out = m(J, D, alpha)
    losses = total_loss(out.I, target, J, out.A, out.B, out.B_frac, D, alpha, m.depth_scale.item(), LossWeights())
    for k, v in losses.items():
        assert torch.isfinite(v), k
    losses["total"].backward()
    grads = [J.grad, D.grad] + [p.grad for p in m.parameters() if p.requires_grad and p.grad is not None]
    assert all(torch.isfinite(gr).all() for gr in grads)
