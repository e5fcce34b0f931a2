"""The fast ``cpu`` backend against the ``torch`` reference: forward values and gradients of every input.

Tolerances: forward max abs difference <= 1e-4 (the brief's bar; measured ~3e-7). Gradients: max abs difference
<= 1e-3 of the largest reference gradient of that parameter ("rel 1e-3" on the gradient's scale; measured ~1e-6).
An element-wise relative test would be meaningless for the many near-zero entries, whose float32 sums of
hundreds of terms carry ~1e-7 absolute noise. Both backends make identical discrete decisions (alpha >= 1/255
is decided on bit-identical float32 sigma; see ``_torch_ref``), so no pixel may differ by a whole Gaussian.
"""

from __future__ import annotations

import pytest
import torch

from pipeline.splat.random_scene import RandomScene, pinhole_K, random_scene
from pipeline.splat.rasterize import rasterize

W, H = 64, 48
NAMES = ("means", "quats", "scales", "opacities", "colors")


def _run(scene: RandomScene, backend: str, seed: int = 7, bg_grad: bool = False, **kw):
    """Render, backprop random cotangents on colour and alpha; return outputs and all gradients."""
    params = [p.detach().clone().requires_grad_() for p in scene.params()]
    bg = kw.pop("backgrounds", None)
    if bg is not None:
        bg = bg.detach().clone().requires_grad_(bg_grad)
    img, alpha, info = rasterize(
        *params, scene.viewmats, scene.Ks, scene.width, scene.height, backgrounds=bg, backend=backend, **kw
    )
    g = torch.Generator().manual_seed(seed)
    loss = (img * torch.rand(img.shape, generator=g)).sum() + (alpha * torch.rand(alpha.shape, generator=g)).sum()
    loss.backward()
    grads = {n: p.grad for n, p in zip(NAMES, params)}
    grads["means2d"] = info["means2d"].grad
    if bg_grad:
        grads["backgrounds"] = bg.grad
    return img.detach(), alpha.detach(), grads, info


def assert_grad_close(name: str, got: torch.Tensor | None, ref: torch.Tensor | None, rtol: float = 1e-3) -> None:
    if ref is None or not torch.any(ref != 0):
        assert got is None or float(got.abs().max()) <= 1e-10, f"{name}: expected no gradient"
        return
    assert got is not None, f"{name}: no gradient"
    scale = float(ref.abs().max())
    err = float((got - ref).abs().max())
    assert err <= rtol * scale, f"{name}: max |diff| {err:.3g} > {rtol} * {scale:.3g}"


def assert_backends_agree(scene: RandomScene, check_grads=NAMES + ("means2d",), **kw):
    ci, ca, cg, cinfo = _run(scene, "cpu", **kw)
    ti, ta, tg, tinfo = _run(scene, "torch", **kw)
    assert ci.shape == ti.shape and ca.shape == ta.shape
    assert float((ci - ti).abs().max()) <= 1e-4, float((ci - ti).abs().max())
    assert float((ca - ta).abs().max()) <= 1e-4, float((ca - ta).abs().max())
    assert torch.equal(cinfo["radii"], tinfo["radii"])
    for name in check_grads:
        assert_grad_close(name, cg[name], tg[name])
    return ci, ca, cg, cinfo


def test_random_scene_matches_reference():
    scene = random_scene(3000, W, H, seed=1)
    img, alpha, grads, _ = assert_backends_agree(scene)
    assert float(alpha.mean()) > 0.5  # the scene actually covers the image
    assert all(float(grads[n].abs().max()) > 0 for n in NAMES)


def test_two_cameras_match_reference():
    scene = random_scene(1500, W, H, seed=2)
    R = torch.tensor([[0.9950, 0.0, -0.0998], [0.0, 1.0, 0.0], [0.0998, 0.0, 0.9950]])
    vm2 = torch.eye(4)
    vm2[:3, :3] = R
    vm2[:3, 3] = torch.tensor([0.3, -0.1, 0.2])
    scene.viewmats = torch.stack([scene.viewmats[0], vm2])
    scene.Ks = torch.stack([scene.Ks[0], pinhole_K(W, H, 60.0)])
    img, *_ = assert_backends_agree(scene)
    assert img.shape == (2, H, W, 3)


def test_behind_camera_and_near_plane():
    scene = random_scene(1500, W, H, seed=3)
    scene.means[:500, 2] -= 4.5  # z in [-1.5, 0.5]: behind, straddling the near plane, just in front
    _, _, _, info = assert_backends_agree(scene)
    behind = scene.means[:, 2] < 0.01
    assert behind.any() and (info["radii"][0][behind] == 0).all()


def test_straddling_image_border():
    scene = random_scene(1500, W, H, seed=4)
    # push means onto the four image borders (x = +-1.6 * z * tan(fov/2) ...)
    z = scene.means[:, 2]
    half_w = z * (W / 2) / scene.Ks[0, 0, 0]
    half_h = z * (H / 2) / scene.Ks[0, 1, 1]
    sign = torch.where(torch.arange(1500) % 2 == 0, 1.0, -1.0)
    scene.means[:750, 0] = sign[:750] * half_w[:750] * (1 + 0.05 * torch.randn(750))
    scene.means[750:, 1] = sign[750:] * half_h[750:] * (1 + 0.05 * torch.randn(750))
    assert_backends_agree(scene)


def test_near_degenerate_scales():
    scene = random_scene(1000, W, H, seed=5)
    scene.scales[:300] = 1e-6  # points: the eps2d blur keeps them one pixel wide
    scene.scales[300:600, 2] = 1e-6  # flat discs
    assert_backends_agree(scene)


def test_huge_gaussians_covering_the_image():
    scene = random_scene(200, W, H, seed=6)
    scene.scales[:20] = 3.0  # each covers the whole image
    scene.opacities[:20] = 0.3
    assert_backends_agree(scene)


def test_opacity_near_one_terminates_early():
    scene = random_scene(3000, W, H, seed=7, opacity=(0.97, 0.999))
    _, alpha, _, _ = assert_backends_agree(scene)
    # T < 1e-4 was reached: the 1 - alpha of covered pixels sits at the stop threshold
    assert float((1 - alpha).min()) < 1e-3


def test_empty_and_single_gaussian():
    empty = random_scene(0, W, H)
    img, alpha, info = rasterize(*empty.params(), empty.viewmats, empty.Ks, W, H, backend="cpu")
    assert img.shape == (1, H, W, 3) and float(img.abs().max()) == 0 and float(alpha.abs().max()) == 0
    assert info["means2d"].shape == (1, 0, 2) and info["radii"].shape == (1, 0, 2)
    bg = torch.tensor([[0.1, 0.2, 0.3]])
    img, alpha, _ = rasterize(*empty.params(), empty.viewmats, empty.Ks, W, H, backgrounds=bg, backend="cpu")
    assert torch.allclose(img, bg.expand(H, W, 3)[None])
    one = random_scene(1, W, H, seed=8)
    one.means[0] = torch.tensor([0.1, -0.05, 2.0])
    one.scales[0] = torch.tensor([0.05, 0.02, 0.08])  # anisotropic, so the rotation matters
    _, alpha, _, _ = assert_backends_agree(one)
    assert float(alpha.max()) > 0.05


@pytest.mark.parametrize("bg", [(0.0, 0.0, 0.0), (0.2, 0.5, 0.9)])
def test_backgrounds(bg):
    scene = random_scene(1500, W, H, seed=9, opacity=(0.05, 0.5))
    backgrounds = torch.tensor([bg])
    check = NAMES + ("means2d", "backgrounds")
    img, alpha, *_ = assert_backends_agree(scene, check_grads=check, backgrounds=backgrounds, bg_grad=True)
    # where nothing is drawn the pixel is the background
    empty = alpha[0, ..., 0] < 1e-6
    if empty.any():
        assert torch.allclose(img[0][empty], backgrounds.expand(int(empty.sum()), 3), atol=1e-6)


@pytest.mark.parametrize("mode", ["RGB+ED", "ED"])
def test_expected_depth_and_its_gradient(mode):
    scene = random_scene(1500, W, H, seed=10)
    bg = torch.tensor([[0.3, 0.3, 0.3]])
    img, alpha, _, _ = assert_backends_agree(scene, render_mode=mode, backgrounds=bg)
    assert img.shape[-1] == (4 if mode == "RGB+ED" else 1)
    depth = img[..., -1]
    covered = alpha[..., 0] > 0.5
    assert float(depth[covered].min()) > 2.9 and float(depth[covered].max()) < 5.1  # the scene's z range
    # a loss on depth alone (what the medium model backprops): every geometric input gets the same gradient
    grads = {}
    for backend in ("cpu", "torch"):
        params = [p.detach().clone().requires_grad_() for p in scene.params()]
        img, _, _ = rasterize(*params, scene.viewmats, scene.Ks, W, H, render_mode=mode, backend=backend)
        (img[..., -1] * torch.linspace(0, 1, W)).sum().backward()
        grads[backend] = [p.grad for p in params]
    for name, got, ref in zip(NAMES[:4], grads["cpu"], grads["torch"]):
        assert_grad_close(f"depth -> {name}", got, ref)
    assert float(grads["cpu"][0][:, 2].abs().max()) > 0


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_degrees(degree):
    scene = random_scene(1500, W, H, seed=11 + degree, sh=True)
    scene.means[:, 0] *= 2.0  # wide spread of view directions
    _, _, grads, _ = assert_backends_agree(scene, sh_degree=degree)
    k = (degree + 1) ** 2
    assert float(grads["colors"][:, :k].abs().max()) > 0
    assert not torch.any(grads["colors"][:, k:] != 0)  # unused bands get no gradient


def test_absgrad_matches_reference():
    scene = random_scene(1500, W, H, seed=20)
    *_, cinfo = _run(scene, "cpu", absgrad=True)
    *_, tinfo = _run(scene, "torch", absgrad=True)
    c_abs, t_abs = cinfo["means2d"].absgrad, tinfo["means2d"].absgrad
    assert_grad_close("absgrad", c_abs, t_abs)
    # |sum| <= sum |.|
    assert bool((cinfo["means2d"].grad.abs() <= c_abs + 1e-6).all())


@pytest.mark.parametrize("channels, mode", [(6, "RGB"), (5, "RGB+ED"), (2, "RGB+ED")])
def test_feature_channel_counts(channels, mode):
    """Any D: the cpu kernels hold 4 channels per pass and render more in groups."""
    scene = random_scene(1000, W, H, seed=30 + channels)
    scene.colors = torch.rand(1000, channels, generator=torch.Generator().manual_seed(channels))
    bg = torch.linspace(0.1, 0.9, channels)[None]
    check = NAMES + ("means2d", "backgrounds")
    img, *_ = assert_backends_agree(scene, check_grads=check, render_mode=mode, backgrounds=bg, bg_grad=True)
    assert img.shape[-1] == channels + (mode == "RGB+ED")
