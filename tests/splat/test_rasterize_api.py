"""The public entry point: input checks, backend selection, lazy imports, the info dict, and gsplat's
DefaultStrategy driven by our backends on CPU tensors."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from pipeline.splat.random_scene import random_scene
from pipeline.splat.rasterize import rasterize

W, H = 64, 48


def _args(n=50, **over):
    s = random_scene(n, W, H, seed=0)
    args = dict(
        means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities, colors=s.colors,
        viewmats=s.viewmats, Ks=s.Ks, width=W, height=H,
    )  # fmt: skip
    args.update(over)
    return args


@pytest.mark.parametrize(
    "over, match",
    [
        ({"means": torch.zeros(50, 2)}, r"means must be \[N, 3\], got \(50, 2\)"),
        ({"quats": torch.zeros(50, 3)}, r"quats must be \[50, 4\] for N=50, got \(50, 3\)"),
        ({"scales": torch.zeros(49, 3)}, r"scales must be \[50, 3\] for N=50, got \(49, 3\)"),
        ({"opacities": torch.zeros(50, 1)}, r"opacities must be \[50\] for N=50, got \(50, 1\)"),
        ({"colors": torch.zeros(51, 3)}, r"colors must be \[N, D\] with N=50"),
        ({"viewmats": torch.eye(4)}, r"viewmats must be \[C, 4, 4\]"),
        ({"Ks": torch.zeros(2, 3, 3)}, r"Ks must be \[C, 3, 3\] for C=1, got \(2, 3, 3\)"),
        ({"width": 0}, r"width and height must be positive integers"),
    ],
)
def test_bad_shapes_raise_value_error_naming_the_shape(over, match):
    with pytest.raises(ValueError, match=match):
        rasterize(**_args(**over), backend="torch")


def test_bad_options_raise_value_error():
    with pytest.raises(ValueError, match=r"SH coefficients \[N, K>=16, 3\] for sh_degree=3"):
        rasterize(**_args(), sh_degree=3)
    with pytest.raises(ValueError, match="sh_degree must be in 0..3"):
        rasterize(**_args(colors=torch.zeros(50, 25, 3)), sh_degree=4)
    with pytest.raises(ValueError, match=r"backgrounds must be \[C, D\] = \[1, 3\], got \(3,\)"):
        rasterize(**_args(), backgrounds=torch.zeros(3))
    with pytest.raises(ValueError, match="render_mode"):
        rasterize(**_args(), render_mode="D")
    with pytest.raises(ValueError, match="backend must be one of"):
        rasterize(**_args(), backend="metal")
    with pytest.raises(ValueError, match="backend 'cuda' needs CUDA tensors"):
        rasterize(**_args(), backend="cuda")


def test_import_is_lazy():
    """Importing the package and the entry point, and rendering with the torch backend, loads neither numba nor
    gsplat (gsplat would try a CUDA JIT build here); the cpu backend loads numba on first use only."""
    code = (
        "import sys, torch\n"
        "import pipeline.splat, pipeline.splat.rasterize as r, pipeline.splat.project, pipeline.splat.sh\n"
        "from pipeline.splat.random_scene import random_scene\n"
        "s = random_scene(10, 32, 24)\n"
        "r.rasterize(*s.params(), s.viewmats, s.Ks, 32, 24, backend='torch')\n"
        "assert 'numba' not in sys.modules and 'gsplat' not in sys.modules, sorted(sys.modules)\n"
        "r.rasterize(*s.params(), s.viewmats, s.Ks, 32, 24)\n"
        "assert 'numba' in sys.modules and 'gsplat' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_info_dict_has_gsplat_layout():
    params = [p.requires_grad_() for p in random_scene(300, W, H, seed=1).params()]
    s = random_scene(300, W, H, seed=1)
    img, alpha, info = rasterize(*params, s.viewmats, s.Ks, W, H)
    assert info["backend"] == "cpu" and info["tile_size"] == 8
    assert (info["width"], info["height"], info["n_cameras"]) == (W, H, 1)
    assert info["means2d"].shape == (1, 300, 2) and info["radii"].shape == (1, 300, 2)
    assert info["radii"].dtype == torch.int32 and info["depths"].shape == (1, 300)
    assert info["opacities"].shape == (1, 300) and info["gaussian_ids"] is None
    img.sum().backward()
    assert info["means2d"].grad is not None and info["means2d"].grad.shape == (1, 300, 2)
    visible = (info["radii"] > 0).all(-1)
    assert float(info["means2d"].grad[visible].abs().sum()) > 0
    assert not torch.any(info["means2d"].grad[~visible] != 0)


def test_float64_inputs_are_accepted():
    s = random_scene(300, W, H, seed=2)
    params = [p.double().requires_grad_() for p in s.params()]
    img, _, _ = rasterize(*params, s.viewmats.double(), s.Ks.double(), W, H)
    img.sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float64 for p in params)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("absgrad", [False, True])
def test_default_strategy_grows_and_prunes(backend, absgrad):
    from gsplat.strategy import DefaultStrategy

    s = random_scene(400, W, H, seed=3)
    params = torch.nn.ParameterDict({
        "means": s.means, "scales": torch.log(s.scales), "quats": s.quats,
        "opacities": torch.logit(s.opacities), "colors": s.colors,
    })  # fmt: skip
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    strategy = DefaultStrategy(
        refine_start_iter=0, refine_every=3, grow_grad2d=1e-7, prune_opa=0.2, absgrad=absgrad, verbose=False
    )
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    n0 = len(params["means"])
    target = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(0))
    for step in range(4):
        img, _, info = rasterize(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            params["colors"], s.viewmats, s.Ks, W, H, backend=backend, absgrad=absgrad,
        )  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (img - target).abs().mean().backward()
        if absgrad:
            assert info["means2d"].absgrad.shape == info["means2d"].shape
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
    assert len(params["means"]) != n0  # step 3 refined: duplicated / split / pruned


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("sh_degree, bands", [(1, 4), (0, 4), (2, 16)])
def test_sh_bands_apart_render_as_the_coefficients_whole(backend, sh_degree, bands):
    """``colors`` the DC band and ``sh_rest`` the higher bands (as the Gaussians keep them): the same image, alpha
    and gradients, bit for bit, as the concatenated coefficients; bands beyond ``sh_degree`` get zero gradient."""
    g = torch.Generator().manual_seed(11)
    sh = 0.5 * torch.randn(50, bands, 3, generator=g)
    cot = torch.randn(1, H, W, 4, generator=g)
    outs = []
    for apart in (True, False):
        sh0, shN = sh[:, :1].clone().requires_grad_(True), sh[:, 1:].clone().requires_grad_(True)
        colors, rest = (sh0, shN) if apart else (torch.cat([sh0, shN], dim=1), None)
        img, alpha, _ = rasterize(**_args(colors=colors), sh_degree=sh_degree, sh_rest=rest, render_mode="RGB+ED",
                                  backend=backend)
        ((img * cot).sum() + alpha.sum()).backward()
        outs.append((img.detach(), alpha.detach(), sh0.grad, shN.grad))
    for a, b in zip(*outs):
        assert torch.equal(a, b)
    k = (sh_degree + 1) ** 2
    assert float(outs[0][3][:, k - 1:].abs().sum()) == 0.0
    assert float(outs[0][2].abs().max()) > 0.0


def test_bad_sh_rest_is_refused():
    dc = torch.zeros(50, 1, 3)
    with pytest.raises(ValueError, match="sh_rest needs sh_degree"):
        rasterize(**_args(colors=dc), sh_rest=torch.zeros(50, 3, 3))
    with pytest.raises(ValueError, match=r"colors must be the SH DC band \[N, 1, 3\]"):
        rasterize(**_args(colors=torch.zeros(50, 4, 3)), sh_degree=1, sh_rest=torch.zeros(50, 3, 3))
    with pytest.raises(ValueError, match=r"sh_rest must be \[N, K - 1, 3\] with N=50"):
        rasterize(**_args(colors=dc), sh_degree=1, sh_rest=torch.zeros(49, 3, 3))
    with pytest.raises(ValueError, match=r"SH coefficients \[N, K>=9, 3\] for sh_degree=2"):
        rasterize(**_args(colors=dc), sh_degree=2, sh_rest=torch.zeros(50, 3, 3))
