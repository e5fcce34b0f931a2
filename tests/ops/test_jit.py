"""The compiled loss graphs against their eager twins (``pipeline.ops.jit``), forward and backward.

The first compile of each graph costs ~1 min on an empty inductor cache (once per machine and size: the cache is
on disk), so this module compiles three: the homogeneous and the dualphys medium losses, and L1 + SSIM.
"""

from __future__ import annotations

import pytest
import torch

from pipeline.medium.losses import LossWeights
from pipeline.medium.model import Medium
from pipeline.medium.term import ViewEvidence, view_losses
from pipeline.ops import jit
from pipeline.ops.image_losses import photometric_losses

pytestmark = pytest.mark.skipif(not jit.compiler_available(), reason="inductor needs a C++ compiler")

ENABLED = frozenset({"ab", "wat", "edge", "ms", "floater", "surface"})


def _view(h: int, w: int, k: int, seed: int):
    """A rendered view's tensors (J, alpha, z-depth, photo) and its evidence, random but physically shaped."""
    g = torch.Generator().manual_seed(seed)
    J = (torch.rand(h, w, 3, generator=g) * 0.8).requires_grad_(True)
    alpha = (0.5 + 0.5 * torch.rand(h, w, 1, generator=g)).requires_grad_(True)
    depth = (1.0 + 2.0 * torch.rand(h, w, 1, generator=g)).requires_grad_(True)
    target = torch.rand(h, w, 3, generator=g)
    ray = 1.0 + 0.1 * torch.rand(1, 1, h, w, generator=g)
    pixels = torch.randperm(h * w, generator=g)[:k]
    ranges = 1.0 + 2.0 * torch.rand(k, generator=g)
    range_map = 1.5 + torch.rand(1, 1, h // 4, w // 4, generator=g)
    cover_map = 1.5 + torch.rand(1, 1, h // 4, w // 4, generator=g)
    fitted = (torch.rand(1, 1, h // 4, w // 4, generator=g) < 0.7).float()  # the plane fit held in most cells
    return (J, alpha, depth, target), ViewEvidence(ray, pixels, ranges, range_map, cover_map, fitted)


def _estimate() -> dict[str, torch.Tensor]:
    return {"beta_D": torch.tensor([0.4, 0.15, 0.1]).reshape(1, 3, 1, 1),
            "beta_B": torch.tensor([0.35, 0.2, 0.1]).reshape(1, 3, 1, 1),
            "B_inf": torch.tensor([0.1, 0.35, 0.4]).reshape(1, 3, 1, 1)}


def _losses_and_grads(fn, medium, tensors, ev, estimate, depth_scale):
    for t in tensors[:3]:
        t.grad = None
    medium.zero_grad(set_to_none=True)
    terms, beta = fn(medium, *tensors, ev, estimate, depth_scale, LossWeights(), 1.2, 0.8, ENABLED)
    sum(terms.values()).backward()
    grads = {"J": tensors[0].grad, "alpha": tensors[1].grad, "depth": tensors[2].grad}
    grads.update({n: p.grad for n, p in medium.named_parameters() if p.grad is not None})
    return {k: v.detach() for k, v in terms.items()}, beta, {k: v.clone() for k, v in grads.items()}


@pytest.mark.slow  # inductor compiles the medium's graph: 40-85 s
@pytest.mark.parametrize("mode", ["homogeneous", "dualphys"])
def test_compiled_medium_losses_match_the_eager_twin(mode):
    """Every weighted term within 1e-5 (relative) of eager's, and every gradient (the render's and the
    medium's parameters) within 1e-3 of its largest value (eager and compiled sum in different orders, and
    may pick other subgradients at a max or an abs). As in a job: one image size, views with different counts of
    sparse-point pixels sharing one graph (no recompile)."""
    from torch._dynamo.utils import counters

    torch.manual_seed(0)
    medium = Medium(mode, depth_scale=2.0)
    compiled = jit.Compiled(view_losses)
    graphs = []
    for tensors, ev in (_view(24, 32, 40, 1), _view(24, 32, 17, 2)):
        jit.dynamic_rows(ev.pixels), jit.dynamic_rows(ev.ranges)
        t_e, b_e, g_e = _losses_and_grads(view_losses, medium, tensors, ev, _estimate(), 2.0)
        t_c, b_c, g_c = _losses_and_grads(compiled, medium, tensors, ev, _estimate(), 2.0)
        graphs.append(counters["stats"]["unique_graphs"])
        assert compiled.failed is None
        assert set(t_e) == set(t_c)
        for k in t_e:
            assert torch.allclose(t_c[k], t_e[k], rtol=1e-5, atol=1e-7), (k, float(t_c[k]), float(t_e[k]))
        assert torch.allclose(b_c, b_e, rtol=1e-6)
        assert set(g_e) == set(g_c)
        for k in g_e:
            scale = float(g_e[k].abs().max()) or 1.0
            assert float((g_c[k] - g_e[k]).abs().max()) <= 1e-3 * scale, k
    assert graphs[1] == graphs[0]  # 17 points after 40: the same graph


def test_compiled_photometric_loss_matches_the_eager_twin():
    g = torch.Generator().manual_seed(4)
    compiled = jit.Compiled(photometric_losses)
    for _ in range(2):
        render = torch.rand(30, 41, 3, generator=g).requires_grad_(True)
        target = torch.rand(30, 41, 3, generator=g)
        grads = []
        for fn in (photometric_losses, compiled):
            render.grad = None
            terms = fn(render, target, 0.2)
            sum(terms.values()).backward()
            grads.append((terms, render.grad.clone()))
        (t_e, g_e), (t_c, g_c) = grads
        for k in t_e:
            assert torch.allclose(t_c[k], t_e[k], rtol=1e-5), k
        assert float((g_c - g_e).abs().max()) <= 1e-4 * float(g_e.abs().max())
    assert compiled.failed is None


def test_a_failed_compile_falls_back_to_the_eager_function_for_good():
    """A compiler that fails (here a backend that raises) costs a warning, not the step: the same call returns
    the eager result, and every later call runs eagerly without trying again."""
    tries = []

    def broken_backend(gm, example_inputs):
        tries.append(1)
        raise RuntimeError("no compiler today")

    def double(x):
        return x * 2

    wrapped = jit.Compiled(double, backend=broken_backend)
    x = torch.ones(3, requires_grad=True)
    assert torch.equal(wrapped(x), x * 2)
    assert wrapped.failed is not None and "no compiler today" in wrapped.failed
    assert torch.equal(wrapped(x + 1), (x + 1) * 2)
    assert len(tries) == 1  # not tried again


def test_the_rule_compiles_long_runs_only():
    assert jit.should_compile("auto", jit.MIN_ITERATIONS)
    assert not jit.should_compile("auto", jit.MIN_ITERATIONS - 1)
    assert jit.should_compile("on", 10)
    assert not jit.should_compile("off", 100_000)
    with pytest.raises(ValueError, match="compile_losses"):
        jit.should_compile("sometimes", 100)
