"""A trained model rebuilt from its checkpoint: the Gaussians, the medium module, the SH degree and background
it was trained with. Rendering it is :func:`pipeline.train.render.render_outputs`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from pipeline.config import MediumConfig, from_dict
from pipeline.job.layout import JobLayout
from pipeline.medium.model import Medium
from pipeline.scene.loader import load_scene
from pipeline.scene.records import View, scaled_view
from pipeline.train.setup import rendered_sh_degree


def medium_from_state(mode: str, sd: dict[str, Any]) -> Medium:
    """Rebuild the trained medium module from a checkpoint's ``"medium"`` entry."""
    cfg = from_dict(MediumConfig, sd["config"])
    m = Medium.from_config(mode, cfg, sd["depth_scale"])
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
    colour_space: str = "srgb"  # where its physics ran: "linear" renders J and I in linear light (render.displayed)


def training_views(job: Path, state: dict) -> list[View]:
    """The job's cameras at the resolution its model was trained at."""
    down = int(state["config"].get("downscale", 1))
    return [scaled_view(v, down) for v in load_scene(JobLayout(job).scene).views]


def model_from_state(state: dict[str, Any]) -> TrainedModel:
    """The renderable model in a training checkpoint ``state`` (``pipeline.train.checkpoint.load_checkpoint``)."""
    cfg = state["config"]
    medium = medium_from_state(state["mode"], state["medium"]) if state.get("medium") else None
    sh = rendered_sh_degree(cfg.get("sh_degree", 3), cfg["medium"].get("max_sh_degree", 1) if medium is not None
                            else None)
    # Medium modes render J premultiplied over black (the water fills what the Gaussians leave uncovered).
    background = (0.0, 0.0, 0.0) if medium is not None else tuple(cfg.get("background", (0.0, 0.0, 0.0)))
    return TrainedModel(state["mode"], dict(state["gaussians"]), medium, sh, background,  # type: ignore[arg-type]
                        cfg.get("colour_space", "srgb"))
