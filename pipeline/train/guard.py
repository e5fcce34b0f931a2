"""Training that knows when its model failed: train, measure the model (``pipeline.train.quality``), and when it lost
its scene retrain once on a safer schedule; if that also loses it, fail with ``model_collapsed``.

Never ``done`` with a blank model: a job whose Gaussians vanished into the water used to end with a
plausible held-out PSNR (the veil alone matches murky photos) and black restorations.

Resumable: ``JobLayout.recovery`` records that the first attempt collapsed (its checkpoint is kept as
``JobLayout.collapsed``), so a resumed stage continues the safer attempt instead of repeating the first.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from pipeline.config import TrainConfig
from pipeline.job.layout import CHECKPOINT_NAME, COLLAPSED_NAME, RECOVERY_NAME
from pipeline.medium.losses import LossWeights
from pipeline.scene.records import Scene, View
from pipeline.train.budget import pixel_budget
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.quality import assess_state
from pipeline.train.setup import prepare_images
from pipeline.train.targets import AsNumpy
from pipeline.train.trainer import TrainResult, train

log = logging.getLogger(__name__)

SAFER_SURFACE_FACTOR = 5.0  # the surface term's weight in the safer schedule, x the default
SAFER_MEDIUM_START = 0.5  # the medium switches on no earlier than half-way in the safer schedule
MIN_GUARDED_ITERATIONS = 1000  # shorter runs (quick looks, tests) are measured and warned about, never retried:
#                                a model a few hundred steps old has not covered its views yet, it has not lost them


class ModelCollapsedError(RuntimeError):
    """The trained model lost its scene, also after the safer retry; the checkpoints are kept."""

    code = "model_collapsed"


def safer_config(cfg: TrainConfig) -> tuple[TrainConfig, dict[str, Any]]:
    """The retry's config and what it changed: no opacity reset at all, the medium on later, the sparse points'
    surface term stronger. Only the schedule and the surface term change, never the data or the mode."""
    weights = dict(cfg.medium.loss_weights)
    weights["w_surface"] = SAFER_SURFACE_FACTOR * weights.get("w_surface", LossWeights().w_surface)
    medium = replace(cfg.medium, start_fraction=max(cfg.medium.start_fraction, SAFER_MEDIUM_START),
                     loss_weights=weights)
    c = replace(cfg, densify=replace(cfg.densify, reset_every=cfg.iterations + 1), medium=medium)
    changes = {"opacity_reset": "off", "medium_start_fraction": medium.start_fraction,
               "w_surface": weights["w_surface"]}
    return c, changes


def gaussian_budget(views: Sequence[View], cap: int) -> int:
    """What the Gaussian count is judged against: ``pixel_budget`` of the training pixels (about twice what
    published 3DGS runs end with, ``pipeline.train.budget``), never above the run's cap (0 = none). Not the cap
    alone: a preset's cap is the same for 12 thumbnails and 300 frames."""
    per_pixel = pixel_budget(sum(v.camera.width * v.camera.height for v in views))
    return min(cap, per_pixel) if cap > 0 else per_pixel


def _assess(ckpt: Path, scene: Scene, images: Sequence, cfg: TrainConfig) -> dict:
    state = load_checkpoint(ckpt)
    views, targets = prepare_images(scene.views, images, cfg.downscale, torch.device("cpu"))
    quality = assess_state(state, scene, views, gaussian_budget(views, cfg.densify.max_gaussians), cfg.backend,
                           AsNumpy(targets))  # one view made float at a time
    # the run's own densification cap: above the budget in the explicit modes, whose cap is the preset's
    return {**quality, "cap": int(cfg.densify.max_gaussians)}


def train_checked(scene: Scene, images: Sequence, cfg: TrainConfig, checkpoint_dir: str | Path, *,
                  min_iterations: int = MIN_GUARDED_ITERATIONS, **train_kwargs: Any
                  ) -> tuple[TrainResult, dict, dict | None]:
    """:func:`~pipeline.train.trainer.train` with the collapse check.
    Returns (result, quality, recovery); ``recovery`` is
    None when the first attempt held its scene, else what happened (the first attempt's warnings, the changes).
    Raises :class:`ModelCollapsedError` when the safer attempt collapses too. Runs shorter than
    ``min_iterations`` are measured and warned about but never retried or failed."""
    out = Path(checkpoint_dir)
    rec_path = out / RECOVERY_NAME
    recovery = json.loads(rec_path.read_text()) if rec_path.is_file() else None
    if recovery is None:
        res = train(scene, images, cfg, checkpoint_dir=out, **train_kwargs)
        quality = _assess(out / CHECKPOINT_NAME, scene, images, cfg)
        if not quality["collapsed"]:
            return res, quality, None
        if cfg.iterations < min_iterations:
            quality["warnings"].append(f"a run of {cfg.iterations} iterations is too short to judge (under "
                                       f"{min_iterations}): not retried")
            return res, quality, None
        log.warning("mode %s lost the scene (%s); retraining on a safer schedule", cfg.mode,
                    "; ".join(quality["warnings"]))
        os.replace(out / CHECKPOINT_NAME, out / COLLAPSED_NAME)
        _, changes = safer_config(cfg)
        recovery = {"attempt": 2, "first_attempt": {"mode": cfg.mode, "warnings": quality["warnings"],
                                                    "n_gaussians": quality["n_gaussians"],
                                                    "point_coverage_min": quality["point_coverage_min"],
                                                    "checkpoint": COLLAPSED_NAME},
                    "changes": changes}
        tmp = rec_path.with_name(rec_path.name + ".tmp")
        tmp.write_text(json.dumps(recovery, indent=2))
        os.replace(tmp, rec_path)
    safe, _ = safer_config(cfg)
    res = train(scene, images, safe, checkpoint_dir=out, **train_kwargs)
    quality = _assess(out / CHECKPOINT_NAME, scene, images, safe)
    if quality["collapsed"]:
        raise ModelCollapsedError(
            f"the {cfg.mode} model lost the scene ({'; '.join(quality['warnings'])}), also after a retry on a "
            f"safer schedule ({', '.join(f'{k} {v}' for k, v in recovery['changes'].items())}); both checkpoints "
            f"are kept ({out.name}/{COLLAPSED_NAME}, {out.name}/{CHECKPOINT_NAME})")
    quality["warnings"] = [f"recovered: the first {cfg.mode} attempt lost the scene "
                           f"({'; '.join(recovery['first_attempt']['warnings'])}); retrained on a safer schedule"
                           ] + quality["warnings"]
    return res, quality, recovery
