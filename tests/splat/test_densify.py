"""Densification on CPU through gsplat's strategy: clone, split, prune, opacity reset, growth cap, state."""

from __future__ import annotations

import math

import torch
from torch import nn

from pipeline.config import DensifyConfig
from pipeline.splat.densify import Densifier
from pipeline.splat.gaussians import make_gaussians

W = H = 100


def toy_gaussians(n_per_group: int = 10) -> tuple[nn.ParameterDict, torch.Tensor]:
    """Four groups of ``n_per_group`` Gaussians (scene scale 1, grow_scale3d 0.01):
    A small + high gradient -> cloned; B large + high gradient -> split;
    C transparent + low gradient -> pruned; D ordinary + low gradient -> untouched.
    Returns the parameters and the per-Gaussian weight a_i of the toy loss sum_i a_i * u_i."""
    g = torch.Generator().manual_seed(0)
    n = 4 * n_per_group
    scale = torch.full((n, 3), math.log(0.003))
    scale[n_per_group : 2 * n_per_group] = math.log(0.05)
    opac = torch.full((n,), 0.0)  # opacity 0.5
    opac[2 * n_per_group : 3 * n_per_group] = math.log(0.001 / 0.999)
    params = make_gaussians(
        torch.rand(n, 3, generator=g), scale, torch.tensor([1.0, 0, 0, 0]).repeat(n, 1), opac,
        torch.zeros(n, 1, 3), torch.zeros(n, 3, 3),
    )  # fmt: skip
    # NDC-normalised gradient norm = a_i * W / 2: high 5e-3 (> 2e-4), low 5e-6. A ramp makes them distinct.
    a = torch.full((n,), 1e-7)
    a[: 2 * n_per_group] = 1e-4 * (1 + torch.arange(2 * n_per_group) / (2 * n_per_group))
    return params, a


def optimizers_for(params: nn.ParameterDict) -> dict[str, torch.optim.Optimizer]:
    """lr 0: Adam builds its state (which the surgery must carry) but values stay put, so counts are exact."""
    return {k: torch.optim.Adam([{"params": [p], "lr": 0.0, "name": k}], eps=1e-15) for k, p in params.items()}


def one_step(densifier, params, optimizers, step: int, a: torch.Tensor):
    n = len(params["means"])
    means2d = (params["means"][:, :2] * 100.0)[None]  # [C=1, N, 2], a stand-in projection
    info = {"means2d": means2d, "radii": torch.ones(1, n, 2, dtype=torch.int32), "width": W, "height": H,
            "n_cameras": 1}  # fmt: skip
    densifier.pre_backward(params, optimizers, step, info)
    a = torch.cat([a, torch.full((max(0, n - len(a)),), 1e-7)])[:n]  # new Gaussians: low gradient
    loss = (a * means2d[0, :, 0]).sum() + 1e-3 * sum(p.sum() for p in params.values())
    loss.backward()
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    return densifier.post_backward(params, optimizers, step, info)


def test_clone_split_prune_counts():
    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    medium = nn.Linear(3, 3)  # medium parameters live outside the Gaussian dict: never touched
    medium_before = medium.weight.detach().clone()
    cfg = DensifyConfig(refine_start=0, refine_every=5, refine_stop=100, reset_every=1000)
    dens = Densifier(cfg, scene_scale=1.0)
    dens.check(params, optimizers)
    events = [one_step(dens, params, optimizers, s, a) for s in range(1, 6)]
    assert events[:4] == [None] * 4
    ev = events[4]
    assert (ev.duplicated, ev.split, ev.pruned, ev.opacity_reset) == (10, 10, 10, False)
    # 40 + 10 clones + 10 splits (each replaces 1 by 2) - 10 pruned
    assert ev.n_gaussians == 50 == len(params["means"])
    for k, p in params.items():
        assert p.shape[0] == 50
        st = optimizers[k].state[p]
        assert st["exp_avg"].shape == p.shape and optimizers[k].param_groups[0]["params"][0] is p
    assert dens.state["grad2d"].shape == (50,) and float(dens.state["grad2d"].abs().sum()) == 0.0
    # split children get scale / 1.6; clones keep theirs
    scales = torch.exp(params["scales"].detach()).max(dim=1).values
    assert int(torch.isclose(scales, torch.tensor(0.05 / 1.6)).sum()) == 20
    assert int(torch.isclose(scales, torch.tensor(0.003)).sum()) == 30  # 10 A + 10 clones + 10 D
    assert torch.sigmoid(params["opacities"].detach()).min() > 0.005
    assert torch.equal(medium.weight.detach(), medium_before)
    one_step(dens, params, optimizers, 6, a)  # training continues on the new tensors
    assert len(params["means"]) == 50


def test_opacity_reset_fires():
    """3DGS resets opacities every reset_every iterations (gsplat 1.5.3's own condition never fires)."""
    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    dens = Densifier(DensifyConfig(refine_start=50, refine_every=5, refine_stop=100, reset_every=3), 1.0)
    events = [one_step(dens, params, optimizers, s, a) for s in range(1, 4)]
    assert events[:2] == [None, None] and events[2].opacity_reset and events[2].duplicated == 0
    assert float(torch.sigmoid(params["opacities"].detach()).max()) <= 0.01 + 1e-6
    assert float(optimizers["opacities"].state[params["opacities"]]["exp_avg"].abs().max()) == 0.0


def test_upstream_default_strategy_never_resets_opacity():
    """Pins the upstream bug our subclass works around (gsplat PR #776). If this fails, gsplat fixed it and
    the override in pipeline/splat/densify.py can go."""
    from gsplat.strategy import DefaultStrategy

    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    strategy = DefaultStrategy(refine_start_iter=50, refine_every=5, refine_stop_iter=100, reset_every=3)
    state = strategy.initialize_state(scene_scale=1.0)
    for step in range(1, 4):
        means2d = (params["means"][:, :2] * 100.0)[None]
        info = {"means2d": means2d, "radii": torch.ones(1, 40, 2, dtype=torch.int32), "width": W, "height": H,
                "n_cameras": 1, "gaussian_ids": None}  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (a * means2d[0, :, 0]).sum().backward()
        strategy.step_post_backward(params, optimizers, state, step, info)
    assert float(torch.sigmoid(params["opacities"].detach()).max()) == 0.5


def test_growth_cap_keeps_largest_gradients():
    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    cfg = DensifyConfig(refine_start=0, refine_every=5, refine_stop=100, reset_every=1000, max_gaussians=45)
    dens = Densifier(cfg, scene_scale=1.0)
    ev = [one_step(dens, params, optimizers, s, a) for s in range(1, 6)][-1]
    # room for 5: the 5 largest gradients are the last 5 of group B (ramp), all large -> split
    assert (ev.duplicated, ev.split, ev.pruned) == (0, 5, 10)
    assert len(params["means"]) == 35


def test_state_dict_round_trip():
    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    cfg = DensifyConfig(refine_start=0, refine_every=5, refine_stop=100, reset_every=1000)
    dens = Densifier(cfg, scene_scale=2.5)
    for s in range(1, 4):
        one_step(dens, params, optimizers, s, a)
    sd = dens.state_dict()
    other = Densifier(cfg, scene_scale=1.0)
    other.load_state_dict(sd)
    assert other.state["scene_scale"] == 2.5
    assert torch.equal(other.state["grad2d"], dens.state["grad2d"])
    assert torch.equal(other.state["count"], torch.full((40,), 3.0))


def test_no_opacity_reset_after_stop_resets_at():
    """Medium modes stop resets before the medium starts (an uncovered pixel then shows the veil, and a reset
    scene is not brought back: docs/DECISIONS.md)."""
    params, a = toy_gaussians()
    optimizers = optimizers_for(params)
    dens = Densifier(DensifyConfig(refine_start=50, refine_every=5, refine_stop=100, reset_every=3), 1.0)
    dens.stop_resets_at(5)
    events = [one_step(dens, params, optimizers, s, a) for s in range(1, 10)]
    resets = [e.iteration for e in events if e is not None and e.opacity_reset]
    assert resets == [3]


def test_one_camera_bookkeeping_equals_gsplats():
    """The masked-add ``_update_state`` (one camera) gives gsplat's running sums bit for bit, over a few steps with
    some Gaussians off screen; two cameras take gsplat's own path."""
    from gsplat.strategy import DefaultStrategy

    gen = torch.Generator().manual_seed(3)
    n = 5000
    ours = Densifier(DensifyConfig(), scene_scale=1.0)
    ref = DefaultStrategy(absgrad=False, verbose=False)
    ref_state = ref.initialize_state(scene_scale=1.0)
    params = {"means": torch.zeros(n, 3)}
    for c in (1, 1, 1, 2):
        means2d = torch.randn(c, n, 2, generator=gen).requires_grad_(True)
        means2d.grad = torch.randn(c, n, 2, generator=gen) * 1e-3
        radii = torch.randint(0, 4, (c, n, 2), generator=gen, dtype=torch.int32)  # 0: off screen in that axis
        info = {"means2d": means2d, "radii": radii, "width": 320, "height": 240, "n_cameras": c,
                "gaussian_ids": None}
        ours.strategy._update_state(params, ours.state, info)
        ref._update_state(params, ref_state, info)
        for k in ("grad2d", "count"):
            torch.testing.assert_close(ours.state[k], ref_state[k], rtol=0, atol=0, msg=k)
    assert float(ours.state["count"].max()) >= 4  # every step counted
