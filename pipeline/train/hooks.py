"""Small callbacks run after every training step: progress, log lines, checkpoints, held-out PSNR.

A hook is ``hook(trainer, metrics)``; it may add keys to ``metrics`` (``eval_hook`` adds ``test_psnr``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from torch import Tensor

from pipeline.ops.metrics import pooled_psnr
from pipeline.scene.records import View

if TYPE_CHECKING:
    from pipeline.train.trainer import Trainer

log = logging.getLogger(__name__)

Hook = Callable[["Trainer", dict[str, float]], None]
ProgressFn = Callable[[int, int, dict[str, float]], None]  # (iteration, total, metrics)


def progress_hook(on_progress: ProgressFn) -> Hook:
    """Report every iteration to the caller (the worker throttles its own status writes)."""
    return lambda tr, m: on_progress(tr.iteration, tr.cfg.iterations, m)


def log_hook(every: int) -> Hook:
    def hook(tr: Trainer, m: dict[str, float]) -> None:
        if every > 0 and tr.iteration % every == 0:
            rate = tr.iteration / max(tr.elapsed_s, 1e-9)
            log.info("it %d/%d loss %.4f N %d (%.2f it/s)", tr.iteration, tr.cfg.iterations, m["loss"],
                     int(m["n_gaussians"]), rate)  # fmt: skip

    return hook


def checkpoint_hook(every: int, path: Path) -> Hook:
    """Save every ``every`` iterations (the final save is the caller's, so it is not written twice)."""

    def hook(tr: Trainer, m: dict[str, float]) -> None:
        if every > 0 and tr.iteration % every == 0 and tr.iteration < tr.cfg.iterations:
            tr.save(path)

    return hook


CURVE_POINTS = 8  # held-out PSNR evaluations over a job's training run (the last one is the final model)
CURVE_VIEWS = 3  # at most this many held-out views are rendered for each point (cheap; the evaluate stage
#                  scores every held-out view once, at the end)


def curve_every(iterations: int, points: int = CURVE_POINTS) -> int:
    """The evaluation interval giving about ``points`` speed-vs-error points over ``iterations`` (the hook also
    evaluates at the last iteration, so the final model is always a point)."""
    return max(1, math.ceil(iterations / max(1, points)))


def curve_subset(n: int, k: int = CURVE_VIEWS) -> list[int]:
    """Indices of at most ``k`` of ``n`` held-out views, evenly spaced (first one included)."""
    if n <= k:
        return list(range(n))
    return sorted({round(i * (n - 1) / (k - 1)) for i in range(k)}) if k > 1 else [0]


def eval_hook(every: int, views: Sequence[View], targets: Sequence[Tensor]) -> Hook:
    """Held-out PSNR every ``every`` iterations and at the end, appended to ``trainer.history`` (the
    speed-vs-error curve: iteration, training seconds, PSNR)."""

    def hook(tr: Trainer, m: dict[str, float]) -> None:
        if (every > 0 and tr.iteration % every == 0) or tr.iteration == tr.cfg.iterations:
            # tr.predict renders what the camera would see: with the water in medium modes.
            psnr = pooled_psnr([(tr.predict(v), t) for v, t in zip(views, targets, strict=True)])
            tr.history.append({"iteration": tr.iteration, "elapsed_s": tr.elapsed_s, "psnr": psnr})
            m["test_psnr"] = psnr
            log.info("it %d held-out PSNR %.2f dB", tr.iteration, psnr)

    return hook
