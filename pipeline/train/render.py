"""Render Gaussian parameters from a posed ``View``: the one place turning parameters into rasterizer inputs
(:func:`render_view`, every training iteration), and through the trained medium (:func:`render_outputs`:
J, the with-water image I, A, B and depth, for export, evaluation, the model check and re-rendering).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.medium.model import Medium
from pipeline.scene.colour import linear_to_srgb
from pipeline.scene.records import View, ray_length_factor
from pipeline.splat.gaussians import activate, sh_degree_of
from pipeline.splat.rasterize import rasterize


@dataclass
class RenderOutput:
    """One rendered view."""

    image: Tensor  # [H, W, 3]
    alpha: Tensor  # [H, W, 1] accumulated opacity
    depth: Tensor | None  # [H, W, 1] alpha-normalised expected depth (render_mode "RGB+ED"), else None
    info: dict[str, Any]  # the rasterizer's bookkeeping (means2d [1, N, 2], radii [1, N, 2], ...)


def view_tensors(view: View, device: torch.device) -> tuple[Tensor, Tensor]:
    """(viewmat [4, 4] world->camera, K [3, 3]) as float32 tensors on ``device``."""
    viewmat = torch.as_tensor(view.viewmat, dtype=torch.float32, device=device)
    K = torch.as_tensor(view.camera.K, dtype=torch.float32, device=device)
    return viewmat, K


def render_gaussians(
    params: nn.ParameterDict | dict[str, Tensor],
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int,
    background: Tensor,  # [3]
    backend: str = "auto",
    render_mode: Literal["RGB", "RGB+ED"] = "RGB",
) -> RenderOutput:
    """Rasterize with SH bands up to ``sh_degree`` (the active degree during warm-up). Differentiable."""
    g = activate(params)
    out, alpha, info = rasterize(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.sh0,  # [N, 1, 3]; the bands above it apart (sh_rest): the rasterizer reads those up to sh_degree
        viewmat[None],
        K[None],
        width,
        height,
        sh_degree=sh_degree,
        sh_rest=g.shN,
        backgrounds=background[None],
        render_mode=render_mode,
        backend=backend,
    )
    depth = out[0, ..., 3:4] if render_mode == "RGB+ED" else None
    return RenderOutput(image=out[0, ..., :3], alpha=alpha[0], depth=depth, info=info)


def render_view(
    params: nn.ParameterDict | dict[str, Tensor],
    view: View,
    *,
    sh_degree: int | None = None,
    background: tuple[float, float, float] | Tensor = (0.0, 0.0, 0.0),
    backend: str = "auto",
    render_mode: Literal["RGB", "RGB+ED"] = "RGB",
) -> RenderOutput:
    """Render ``params`` from ``view`` at the view camera's resolution; ``sh_degree`` defaults to all bands.

    Gradients flow as usual; wrap in ``torch.no_grad()`` for evaluation.
    """
    device = params["means"].device
    viewmat, K = view_tensors(view, device)
    bg = torch.as_tensor(background, dtype=torch.float32, device=device).reshape(3)
    degree = sh_degree_of(params) if sh_degree is None else sh_degree
    return render_gaussians(
        params,
        viewmat,
        K,
        view.camera.width,
        view.camera.height,
        sh_degree=degree,
        background=bg,
        backend=backend,
        render_mode=render_mode,
    )


@dataclass
class ViewOutputs:
    J: np.ndarray  # [H, W, 3] restored radiance
    I: np.ndarray  # noqa: E741  [H, W, 3] with water
    A: np.ndarray | None  # [H, W, 3] attenuation (direct transmission)
    B: np.ndarray | None  # [H, W, 3] backscatter
    depth: np.ndarray  # [H, W] camera-space z, scene units (0 where nothing was rendered)
    alpha: np.ndarray  # [H, W]


def displayed(out: ViewOutputs, colour_space: str) -> ViewOutputs:
    """``out`` with J and I as the photos hold them (sRGB-encoded) for a model whose physics ran in linear light;
    ``out`` itself for ``"srgb"``. A and B stay what the medium computed (transmission and backscatter in the
    model's own space)."""
    if colour_space == "srgb":
        return out
    if colour_space != "linear":
        raise ValueError(f"unknown colour space {colour_space!r}")
    return ViewOutputs(linear_to_srgb(out.J).astype(np.float32), linear_to_srgb(out.I).astype(np.float32), out.A,
                       out.B, out.depth, out.alpha)


def render_outputs(gaussians: dict[str, torch.Tensor], view: View, medium: Medium | None, sh_degree: int,
                   backend: str = "auto", background: tuple[float, float, float] | torch.Tensor = (0.0, 0.0, 0.0),
                   ) -> ViewOutputs:
    """Everything the user can look at for one view (the one place a view is rendered through the medium)."""
    with torch.no_grad():
        out = render_view(gaussians, view, sh_degree=sh_degree, backend=backend, render_mode="RGB+ED",
                          background=background)
        assert out.depth is not None
        J = out.image.clamp(0, 1)
        alpha, z = out.alpha[..., 0], out.depth[..., 0]
        if medium is None:
            return ViewOutputs(J.numpy(), J.numpy(), None, None, (z * (alpha > 1e-3)).numpy(), alpha.numpy())
        ray = torch.as_tensor(ray_length_factor(view.camera), dtype=J.dtype)
        mo = medium(out.image.permute(2, 0, 1)[None], (z * ray)[None, None], alpha[None, None])

        def hwc(x: torch.Tensor) -> np.ndarray:
            return x[0].permute(1, 2, 0).clamp(0, 1).numpy()

        return ViewOutputs(J.numpy(), hwc(mo.I), hwc(mo.A), hwc(mo.B), (z * (alpha > 1e-3)).numpy(), alpha.numpy())
