"""Projection and SH: our torch reference against gsplat's pure-torch implementation (an oracle, tests only), and
the numba kernels (forward and hand-written backward) against our torch reference."""

from __future__ import annotations

import pytest
import torch

from pipeline.splat.project import covariance_3d, project_gaussians
from pipeline.splat.random_scene import pinhole_K, random_scene
from pipeline.splat.sh import sh_basis, sh_to_rgb

W, H = 64, 48


def _cameras() -> tuple[torch.Tensor, torch.Tensor]:
    """Two cameras: identity, and a rotated + translated one with another focal length."""
    a = 0.2
    R = torch.tensor([[1.0, 0, 0], [0, torch.cos(torch.tensor(a)), -torch.sin(torch.tensor(a))],
                      [0, torch.sin(torch.tensor(a)), torch.cos(torch.tensor(a))]])  # fmt: skip
    vm = torch.eye(4).repeat(2, 1, 1)
    vm[1, :3, :3] = R
    vm[1, :3, 3] = torch.tensor([0.2, 0.3, -0.5])
    return vm, torch.stack([pinhole_K(W, H), pinhole_K(W, H, 70.0)])


def _scene(n=400, seed=0):
    s = random_scene(n, W, H, seed=seed)
    s.means[: n // 4, 2] -= 3.5  # some behind the camera or straddling the near plane
    s.means[n // 4 : n // 2, :2] *= 3.0  # some off-screen (Jacobian clamp active)
    s.scales[n // 2 : n // 2 + 20] = 1e-6
    return s


def test_projection_matches_gsplat_oracle():
    from gsplat.cuda._torch_impl import _fully_fused_projection

    s = _scene()
    vm, Ks = _cameras()
    ours = project_gaussians(s.means, s.quats, s.scales, None, vm, Ks, W, H)
    radii, means2d, depths, conics, _ = _fully_fused_projection(s.means, covariance_3d(s.quats, s.scales), vm, Ks, W, H)
    vis = (ours.radii > 0).all(-1)
    assert vis.sum() > 200
    # gsplat's torch code uses strict z > near; ours (like gsplat's CUDA kernel) z >= near. Same here.
    assert torch.equal((radii > 0).all(-1), vis)
    assert (ours.radii[vis] - radii[vis]).abs().max() <= 1  # ceil() of float32 (gsplat) vs float64 (ours) values
    assert (ours.radii[vis] != radii[vis]).float().mean() < 0.01
    torch.testing.assert_close(ours.means2d[vis], means2d[vis], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(ours.depths[vis], depths[vis], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(ours.conics[vis], conics[vis], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat_oracle(degree):
    from gsplat.cuda._torch_impl import _eval_sh_bases_fast, _spherical_harmonics

    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(500, 3, generator=g)
    coeffs = torch.randn(500, 16, 3, generator=g)
    unit = dirs / dirs.norm(dim=-1, keepdim=True)
    k = (degree + 1) ** 2
    torch.testing.assert_close(sh_basis(degree, unit), _eval_sh_bases_fast(k, unit), rtol=1e-5, atol=1e-6)
    expect = torch.clamp_min(_spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)
    torch.testing.assert_close(sh_to_rgb(degree, coeffs, dirs), expect, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("sh_degree", [None, 3])
def test_numba_projection_matches_torch(sh_degree):
    from pipeline.splat._cpu_backend import _Project

    s = _scene(600, seed=1)
    vm, Ks = _cameras()
    coeffs = 0.3 * torch.randn(600, 16, 3, generator=torch.Generator().manual_seed(3))
    ps = [t.clone().requires_grad_() for t in (s.means, s.quats, s.scales, coeffs)]
    bands = (ps[3][:, :1], ps[3][:, 1:]) if sh_degree is not None else (torch.zeros(600, 0, 3),) * 2
    m2, con, dep, col, radii, keys = _Project.apply(
        ps[0], ps[1], ps[2], s.opacities, *bands, vm, Ks, W, H, sh_degree, 0.3, 0.01, 1e10,
    )  # fmt: skip
    qs = [t.clone().requires_grad_() for t in (s.means, s.quats, s.scales, coeffs)]
    ref = project_gaussians(qs[0], qs[1], qs[2], s.opacities, vm, Ks, W, H)
    assert torch.equal(radii, ref.radii)
    assert torch.equal(keys, ref.depth_keys)
    # float64 inside both, rounded to float32: equal but for rare last-bit differences
    for got, want in ((m2, ref.means2d), (con, ref.conics), (dep, ref.depths)):
        torch.testing.assert_close(got, want, rtol=2e-7, atol=1e-7)
    g = torch.Generator().manual_seed(4)
    cot = [torch.randn(t.shape, generator=g) for t in (m2, con, dep)]
    loss_c = sum((a * b).sum() for a, b in zip((m2, con, dep), cot))
    loss_r = sum((a * b).sum() for a, b in zip((ref.means2d, ref.conics, ref.depths), cot))
    if sh_degree is not None:
        campos = torch.linalg.inv(vm)[:, :3, 3]
        col_ref = sh_to_rgb(sh_degree, qs[3][None].expand(2, -1, -1, -1), qs[0][None] - campos[:, None])
        torch.testing.assert_close(col, col_ref, rtol=1e-6, atol=1e-6)
        c_cot = torch.randn(col.shape, generator=g)
        loss_c = loss_c + (col * c_cot).sum()
        loss_r = loss_r + (col_ref * c_cot).sum()
    loss_c.backward()
    loss_r.backward()
    n_grads = 4 if sh_degree is not None else 3
    for name, a, b in zip(("means", "quats", "scales", "coeffs"), ps[:n_grads], qs[:n_grads]):
        err = float((a.grad - b.grad).abs().max())
        assert err <= 1e-4 * float(b.grad.abs().max()), (name, err)


@pytest.mark.parametrize("sh_degree", [None, 1])
def test_numba_projection_culls_off_screen_gaussians_as_the_reference_does(sh_degree):
    """The kernel culls off-screen Gaussians on a bound of their radius before computing their covariance: long
    thin Gaussians, rotated at random, whose centres lie in a band around the image (so many exact radii end
    within a pixel of the border) get the reference's radii and outputs, and the backward gives the culled ones
    exactly zero gradient."""
    from pipeline.splat._cpu_backend import _Project

    n = 3000
    g = torch.Generator().manual_seed(7)
    z = 1.0 + 4.0 * torch.rand(n, generator=g)
    uv = torch.rand(n, 2, generator=g) * torch.tensor([3.0, 3.0]) - 1.0  # -1..2 image widths / heights
    means = torch.stack([(uv[:, 0] * W - W / 2) * z / 60.0, (uv[:, 1] * H - H / 2) * z / 60.0, z], dim=1)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 1.5 - 2.5)  # anisotropic, up to metres
    quats = torch.randn(n, 4, generator=g)
    opac = torch.rand(n, generator=g) * 0.99 + 0.005
    vm, Ks = _cameras()
    coeffs = 0.3 * torch.randn(n, 4, 3, generator=g)
    ps = [t.clone().requires_grad_() for t in (means, quats, scales, coeffs)]
    bands = (ps[3][:, :1], ps[3][:, 1:]) if sh_degree is not None else (torch.zeros(n, 0, 3),) * 2
    m2, con, dep, col, radii, keys = _Project.apply(
        ps[0], ps[1], ps[2], opac, *bands, vm, Ks, W, H, sh_degree, 0.3, 0.01, 1e10,
    )  # fmt: skip
    ref = project_gaussians(means, quats, scales, opac, vm, Ks, W, H)
    assert torch.equal(radii, ref.radii) and torch.equal(keys, ref.depth_keys)
    culled = (radii == 0).all(-1).all(0)  # [N]: in both cameras
    visible = (radii > 0).any(-1).any(0)
    assert int(culled.sum()) > n // 4 and int(visible.sum()) > n // 4
    torch.testing.assert_close(m2, ref.means2d, rtol=2e-7, atol=1e-7)
    torch.testing.assert_close(con, ref.conics, rtol=2e-7, atol=1e-7)
    loss = (m2 * torch.randn(m2.shape, generator=g)).sum() + (con * torch.randn(con.shape, generator=g)).sum()
    loss.backward()
    for p in ps[:3]:
        assert torch.equal(p.grad[culled], torch.zeros_like(p.grad[culled]))
        assert bool((p.grad[visible] != 0).any(-1).all())
