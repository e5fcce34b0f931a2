"""float64 gradcheck of every medium module and loss on small inputs."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from pipeline.medium import losses as L
from pipeline.medium.model import Medium

torch.set_default_dtype(torch.float32)


def _inputs(seed: int = 0, h: int = 6, w: int = 5):
    g = torch.Generator().manual_seed(seed)
    J = torch.rand(1, 3, h, w, generator=g, dtype=torch.float64).requires_grad_()
    D = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 3 + 0.5).requires_grad_()
    return J, D


@pytest.mark.parametrize("mode", ["homogeneous", "dualphys"])
def test_medium_module_gradcheck(mode):
    torch.manual_seed(0)
    m = Medium(mode, depth_scale=2.0).double()
    J, D = _inputs()
    alpha = torch.rand(1, 1, 6, 5, dtype=torch.float64).requires_grad_()
    assert gradcheck(lambda j, d, a: m(j, d, a).I, (J, D, alpha), eps=1e-6, atol=1e-5)
    params = [p for p in m.parameters() if p.requires_grad]

    # Parameter gradients: compare autograd against finite differences through a functional call.
    from torch.func import functional_call

    names = [n for n, p in m.named_parameters() if p.requires_grad]
    values = tuple(p.detach().clone().requires_grad_() for p in params)
    assert gradcheck(lambda *ps: functional_call(m, dict(zip(names, ps)), (J.detach(), D.detach())).I, values,
                     eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("name", ["consistency", "attenuation", "scattering", "edge", "ms", "basic", "floater"])
def test_loss_gradcheck(name):
    J, D = _inputs(1, 12, 12)
    g = torch.Generator().manual_seed(2)
    A = torch.rand(1, 3, 12, 12, generator=g, dtype=torch.float64).requires_grad_()
    B = torch.rand(1, 3, 12, 12, generator=g, dtype=torch.float64).requires_grad_()
    T = torch.rand(1, 3, 12, 12, generator=g, dtype=torch.float64)
    alpha = torch.rand(1, 1, 12, 12, generator=g, dtype=torch.float64).requires_grad_() * 0.8 + 0.1
    fns = {
        "consistency": (lambda a, b, d: L.consistency_loss(a, b, d, 2.0), (A, B, D)),
        "attenuation": (L.attenuation_prior, (J,)),
        "scattering": (lambda b: L.scattering_prior(b, T, alpha.detach()), (B,)),
        "edge": (lambda b, d: L.edge_loss(b, d, 2.0), (B, D)),
        "ms": (lambda j: L.multiscale_loss(j, T), (J,)),
        "basic": (lambda j: L.basic_loss(j, T), (J,)),
        "floater": (L.floater_loss, (alpha.detach().requires_grad_(),)),
    }
    fn, args = fns[name]
    assert gradcheck(fn, args, eps=1e-6, atol=1e-5)
