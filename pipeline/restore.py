"""Restored outputs from a trained model: for any view, the restored radiance J, the with-water image I, the
attenuation A, the backscatter B and the depth, written as images named after the view's image stem.

Folders (under ``out``): ``restored/`` (J), ``with_water/`` (I), ``attenuation/`` (A), ``backscatter/`` (B),
``depth/`` (16-bit PNG normalised to the scene's depth range for viewing, plus float32 ``.npy`` of the
camera-space z in scene units). In mode ``3dgs`` there is no medium: J = I and A, B are not written.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import MediumConfig, from_dict
from .medium.model import Medium
from .render_view import render_view
from .scene.types import View, ray_length_factor

log = logging.getLogger(__name__)


@dataclass
class ViewOutputs:
    J: np.ndarray  # [H, W, 3] restored radiance
    I: np.ndarray  # noqa: E741  [H, W, 3] with water
    A: np.ndarray | None  # [H, W, 3] attenuation (direct transmission)
    B: np.ndarray | None  # [H, W, 3] backscatter
    depth: np.ndarray  # [H, W] camera-space z, scene units (0 where nothing was rendered)
    alpha: np.ndarray  # [H, W]


def medium_from_state(mode: str, sd: dict[str, Any]) -> Medium:
    """Rebuild the trained medium module from a checkpoint's ``"medium"`` entry."""
    cfg = from_dict(MediumConfig, sd["config"])
    m = Medium(mode, rgb_attenuation=cfg.rgb_attenuation, multiscale_scattering=cfg.multiscale_scattering,
               gamma=cfg.gamma, lam=cfg.lam, delta=cfg.delta, depth_scale=sd["depth_scale"])
    m.load_state_dict(sd["module"])
    return m.eval()


@dataclass
class TrainedModel:
    """What rendering a trained job needs, rebuilt from its checkpoint (see :func:`model_from_state`)."""

    mode: str
    gaussians: dict[str, torch.Tensor]
    medium: Medium | None  # None in mode 3dgs
    sh_degree: int  # the SH degree the model was trained up to (capped at the medium's limit in medium modes)
    background: tuple[float, float, float]  # what training composited behind the Gaussians


def model_from_state(state: dict[str, Any]) -> TrainedModel:
    """The renderable model in a training checkpoint ``state`` (``pipeline.checkpoint.load_checkpoint``)."""
    cfg = state["config"]
    medium = medium_from_state(state["mode"], state["medium"]) if state.get("medium") else None
    sh = cfg.get("sh_degree", 3)
    if medium is not None:
        sh = min(sh, cfg["medium"].get("max_sh_degree", 1))
    # Medium modes render J premultiplied over black (the water fills what the Gaussians leave uncovered).
    background = (0.0, 0.0, 0.0) if medium is not None else tuple(cfg.get("background", (0.0, 0.0, 0.0)))
    return TrainedModel(state["mode"], dict(state["gaussians"]), medium, sh, background)  # type: ignore[arg-type]


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


EXPORT_FOLDERS = ("restored", "with_water", "depth", "attenuation", "backscatter")  # the last two: medium modes


def export_views(state: dict[str, Any], views: Sequence[View], out: str | Path, backend: str = "auto",
                 what: Sequence[str] | None = None) -> dict:
    """Write the restored outputs of every view from a training checkpoint ``state``; returns counts.
    ``what`` limits the folders written (default: all that the model has; see :data:`EXPORT_FOLDERS`)."""
    from .scene.images import write_image

    out = Path(out)
    model = model_from_state(state)
    medium = model.medium
    results = [(v, render_outputs(model.gaussians, v, medium, model.sh_degree, backend, model.background))
               for v in views]
    zmax = max(float(r.depth.max()) for _, r in results) or 1.0
    folders = ["restored", "with_water", "depth"] + (["attenuation", "backscatter"] if medium is not None else [])
    if what is not None:
        folders = [f for f in folders if f in what]
    for f in folders:
        (out / f).mkdir(parents=True, exist_ok=True)
    for v, r in results:
        stem = Path(v.name).stem
        images = {"restored": r.J, "with_water": r.I, "attenuation": r.A, "backscatter": r.B}
        for f in folders:
            if f == "depth":
                write_image(out / "depth" / f"{stem}.png", np.clip(r.depth / zmax, 0, 1), bits=16)
                np.save(out / "depth" / f"{stem}.npy", r.depth.astype(np.float32))
            else:
                write_image(out / f / f"{stem}.png", images[f])
    log.info("exported %d views (%s) to %s", len(results), ", ".join(folders), out)
    return {"views": len(results), "folders": folders, "depth_max": zmax}
