"""Training: plain 3DGS (mode ``3dgs``) on posed images, with checkpoints, progress and cancellation.

Recipe (graphdeco 3DGS, Kerbl et al. 2023): loss 0.8 L1 + 0.2 (1 - SSIM); Adam (eps 1e-15) with position lr
1.6e-4 -> 1.6e-6 x scene extent (exponential decay over the run), SH DC 2.5e-3, higher bands /20, opacity
0.05, scale 0.005, rotation 0.001; active SH degree +1 every ``sh_degree_interval``; one random view per
iteration (each view once per epoch, seeded); densification by gsplat's strategy (``pipeline.splat.densify``).

Layout: ``Trainer.step`` is one iteration and nothing else; progress, checkpoints and held-out evaluation
are hooks (``pipeline.train.hooks``) run after each step by ``Trainer.run``; ``train`` wires them for the
stage and the worker. Setup pieces (extent, images, schedules, optimisers, init) are in
``pipeline.train.setup``. A medium mode extends ``Trainer.compute_losses`` and fills the ``"medium"`` entry
of the state dict; its parameters never enter ``self.gaussians``, so densification cannot touch them.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.config import TrainConfig, from_dict, medium_densify, to_dict
from pipeline.job.layout import CHECKPOINT_NAME
from pipeline.medium.fall_off import fall_off_to_remove
from pipeline.medium.term import MediumTerm
from pipeline.ops.image_losses import photometric_losses
from pipeline.ops.jit import maybe_compiled, should_compile
from pipeline.profiling import section
from pipeline.scene.records import Scene, View, scaled_view
from pipeline.splat.densify import Densifier
from pipeline.splat.gaussians import GAUSSIAN_KEYS
from pipeline.train.checkpoint import load_checkpoint, save_checkpoint
from pipeline.train.exposure import ViewExposure, exposure_without_water
from pipeline.train.hooks import Hook, ProgressFn, checkpoint_hook, eval_hook, log_hook, progress_hook
from pipeline.train.render import RenderOutput, ViewOutputs, render_gaussians, render_outputs, view_tensors
from pipeline.train.schedule import coarse_iterations
from pipeline.train.setup import (
    ImageLike,
    active_sh_degree,
    initial_gaussians,
    make_optimizers,
    means_lr,
    prepare_images,
    rendered_sh_degree,
    scene_extent,
    shrink_image,
)

log = logging.getLogger(__name__)

__all__ = [
    "CHECKPOINT_NAME",
    "STATE_VERSION",
    "TrainResult",
    "Trainer",
    "TrainingCancelled",
    "train",
]

RESET_RECOVERY_REFINES = 2  # medium modes: the last opacity reset is at least this many refinements before the
#                             medium starts (docs/DECISIONS.md, "The water must not eat the scene")
STATE_VERSION = 1
# Config fields that do not change what is trained: a checkpoint differing only in these still resumes.
_NON_SEMANTIC = {"log_every", "checkpoint_every", "eval_every", "compile_losses"}  # the same model either way


class TrainingCancelled(RuntimeError):
    """``should_cancel()`` returned True; ``checkpoint`` is where the state was saved (None if nowhere)."""

    def __init__(self, iteration: int, checkpoint: Path | None = None) -> None:
        super().__init__(f"training cancelled at iteration {iteration}")
        self.iteration = iteration
        self.checkpoint = checkpoint


@dataclass
class TrainResult:
    gaussians: nn.ParameterDict
    iteration: int
    metrics: dict[str, float]  # of the last step, plus "test_psnr" when held-out views were given
    history: list[dict[str, float]] = field(default_factory=list)  # held-out: iteration, elapsed_s, psnr
    checkpoint: Path | None = None
    elapsed_s: float = 0.0  # training seconds (steps only), summed across resumes
    medium: dict[str, Any] = field(default_factory=dict)  # medium modes: recovered per-channel coefficients
    exposure: dict[str, Any] | None = None  # the training views' learned gains (exposure_record); None: not learned


class Trainer:
    """Owns the Gaussians, their optimisers, the densifier, the RNGs and the iteration counter."""

    def __init__(
        self,
        scene: Scene,
        images: Sequence[ImageLike],  # one [H, W, 3] float image in [0, 1] per scene view
        cfg: TrainConfig,
        *,
        device: torch.device | str = "cpu",
    ) -> None:
        self.cfg = cfg
        self.device = torch.device(device)
        self.views, self.targets = prepare_images(scene.views, images, cfg.downscale, self.device)
        self.extent = scene_extent(self.views)
        torch.manual_seed(cfg.seed)  # gsplat's split samples from the global generator
        # The SH bands the model renders: medium modes keep J view-consistent with low-order SH
        # (MediumConfig.max_sh_degree). Only those are allocated: bands never rendered get no gradient, and Adam,
        # densification and checkpoints would carry them as zeros (36 of 59 floats per Gaussian at degree 3).
        self.max_sh_degree = rendered_sh_degree(cfg.sh_degree, None if cfg.mode == "3dgs" else cfg.medium.max_sh_degree)
        self.gaussians = initial_gaussians(scene, replace(cfg, sh_degree=self.max_sh_degree), self.extent,
                                           self.device)
        self.optimizers = make_optimizers(self.gaussians, cfg, self.extent)
        densify = cfg.densify
        if cfg.mode != "3dgs":  # growth goes on while the medium settles; a job's resolved config has it already
            densify = medium_densify(densify)  # (factor 1.0), a config built by hand (probe, benches) gets it here
        self.densifier = Densifier(densify, scene_scale=self.extent)
        self.densifier.check(self.gaussians, self.optimizers)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)  # [3]
        self.compiled = should_compile(cfg.compile_losses, cfg.iterations)  # the loss graphs (pipeline.ops.jit)
        self._photometric = maybe_compiled(photometric_losses, self.compiled)
        self.medium: MediumTerm | None = None
        if cfg.mode != "3dgs":
            # J is rendered premultiplied over black; uncovered pixels see the water's veiling light instead.
            self.background = torch.zeros(3, device=self.device)
            self.medium = MediumTerm(cfg.mode, cfg.medium, scene, self.views, self.targets, cfg.iterations,
                                     self.device, compiled=self.compiled,
                                     exposure_space=cfg.colour_space if cfg.exposure != "off" else None)
            # Opacity resets only while J alone is fitted, with time to recover before the medium starts: once
            # the water is on, an uncovered pixel shows the veil, and a reset scene is not brought back.
            self.densifier.stop_resets_at(self.medium.start - RESET_RECOVERY_REFINES * cfg.densify.refine_every)
        self.exposure: ViewExposure | None = None
        if cfg.exposure != "off":  # from the water fit's gains where it measured them, held or learned
            est = (self.medium.estimate or {}) if self.medium is not None else {}
            init, evidence = est.get("log_gains"), est.get("exposure_evidence")
            if self.medium is None and cfg.exposure != "fit":  # plain splatting: start from the points' gains
                init, evidence = exposure_without_water(scene, self.views, self.targets, cfg.colour_space)
            changed = init is not None and bool(np.any(init))
            learn = cfg.exposure == "learn" or init is None or (cfg.exposure == "auto" and self.medium is None
                                                                and changed)
            source = ("learned in training" + (", from the sparse points' gains" if changed else "") if learn
                      else "the sparse points' fit, held in training" if changed
                      else "none: the sparse points showed no change between frames")
            self.exposure = ViewExposure(len(self.views), cfg.colour_space, cfg.exposure_lr if learn else 0.0,
                                         cfg.exposure_weight, cfg.iterations, init, self.device, source=source,
                                         evidence=evidence,
                                         fall_off=fall_off_to_remove(est) if self.medium is not None else None)
        self.cameras = [view_tensors(v, self.device) for v in self.views]  # (viewmat [4,4], K [3,3])
        # The coarse start (TrainConfig.coarse_fraction): iterations 1..coarse_until render the views shrunk
        # coarse_downscale times against the targets area-averaged to that size, with the eager losses (a
        # compiled graph per size would cost a compile for a phase this cheap)
        self.coarse_until = coarse_iterations(cfg.iterations, cfg.coarse_fraction,
                                              self.medium.start if self.medium is not None else None)
        self.coarse_views = [scaled_view(v, cfg.coarse_downscale) for v in self.views] if self.coarse_until else []
        self.coarse_cameras = [view_tensors(v, self.device) for v in self.coarse_views]
        self.iteration = 0  # iterations completed
        self.elapsed_s = 0.0
        self.history: list[dict[str, float]] = []
        self._view_gen = torch.Generator().manual_seed(cfg.seed)
        self._bg_gen = torch.Generator().manual_seed(cfg.seed + 1)  # TrainConfig.random_background
        self._view_queue: list[int] = []

    def next_view(self) -> int:
        """Random view; each view once per epoch (graphdeco's shuffled stack), from the seeded generator."""
        if not self._view_queue:
            self._view_queue = torch.randperm(len(self.views), generator=self._view_gen).tolist()
        return self._view_queue.pop()

    def coarse(self, iteration: int) -> bool:
        """Whether ``iteration`` trains at the coarse size (the coarse start)."""
        return iteration <= self.coarse_until

    def render(self, i: int, sh_degree: int, render_mode: str = "RGB", coarse: bool = False) -> RenderOutput:
        viewmat, K = (self.coarse_cameras if coarse else self.cameras)[i]
        cam = (self.coarse_views if coarse else self.views)[i].camera
        return render_gaussians(self.gaussians, viewmat, K, cam.width, cam.height, sh_degree=sh_degree,
                                background=self.background, backend=self.cfg.backend,
                                render_mode=render_mode)  # type: ignore[arg-type]  # fmt: skip

    def medium_on(self, iteration: int) -> bool:
        return self.medium is not None and self.medium.active(iteration)

    def compute_losses(self, out: RenderOutput, i: int) -> dict[str, Tensor]:
        """Named, already weighted loss terms for view ``i``; the step sums them once. The photo is compared at
        neutral exposure (``pipeline.train.exposure``) when the run learns the views' exposure."""
        target, extra = self.targets[i], {}
        if self.exposure is not None:
            target, extra = self.exposure.correct(i, target), {"exposure": self.exposure.penalty(i)}
        if self.medium is not None and self.medium_on(self.iteration + 1):
            assert out.depth is not None
            return {**self.medium.losses(i, out.image, out.alpha, out.depth, target), **extra}
        losses = self._photometric
        if self.coarse(self.iteration + 1):  # the shrunk render against the target area-averaged to its size
            losses, target = photometric_losses, shrink_image(target, *out.image.shape[:2])
        with section("losses: photometric fwd"):
            return {**losses(out.image, target, self.cfg.ssim_weight), **extra}

    def outputs(self, view: View) -> ViewOutputs:
        """Everything the model renders for ``view`` (J, I, A, B, depth, alpha), through the medium once it is on."""
        medium = self.medium.medium if self.medium is not None and self.medium_on(self.iteration) else None
        background = (torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)
                      if self.cfg.random_background and self.medium is None else self.background)
        return render_outputs(self.gaussians, view, medium, self.max_sh_degree, self.cfg.backend, background)

    def predict(self, view: View) -> Tensor:
        """The photo this model predicts for ``view`` (with water in medium modes, and the survey's fall-off where
        training divided it out of the photos), clamped. [H, W, 3]"""
        I = self.outputs(view).I
        if self.exposure is not None:
            I = np.clip(self.exposure.photographed(I), 0.0, 1.0).astype(I.dtype)
        return torch.from_numpy(I)

    def step(self) -> dict[str, float]:
        """One iteration: render a view, loss, backward, Adam, densification."""
        it = self.iteration + 1
        self.optimizers["means"].param_groups[0]["lr"] = means_lr(self.cfg, self.extent, it)
        i, sh_degree = self.next_view(), min(active_sh_degree(self.cfg, it), self.max_sh_degree)
        if self.cfg.random_background and self.medium is None:
            self.background = torch.rand(3, generator=self._bg_gen).to(self.device)
        with section("render"):
            out = self.render(i, sh_degree, "RGB+ED" if self.medium_on(it) else "RGB", self.coarse(it))
        with section("densify"):
            self.densifier.pre_backward(self.gaussians, self.optimizers, it, out.info)
        with section("losses"):
            losses = self.compute_losses(out, i)
            loss = sum(losses.values())
            terms = {k: float(v.detach()) for k, v in losses.items()}
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss at iteration {it}: {terms}")
        with section("backward"):
            loss.backward()
        with section("optimizer"):
            for opt in self.optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
            if self.medium is not None:
                self.medium.step()
            if self.exposure is not None:
                self.exposure.step(it)
        if self.medium is not None:
            grad = out.info["means2d"].grad
            if grad is not None:  # the photo's gradients are A times the scene's: densify on the scene's scale
                grad.mul_(self.medium.densify_gain(i))
        with section("densify"):
            event = self.densifier.post_backward(self.gaussians, self.optimizers, it, out.info)
        self.iteration = it
        metrics = {"loss": float(loss.detach()), **terms, "n_gaussians": float(len(self.gaussians["means"])),
                   "sh_degree": float(sh_degree)}  # fmt: skip
        if event is not None:
            metrics.update(duplicated=float(event.duplicated), split=float(event.split), pruned=float(event.pruned))
        return metrics

    def run(self, hooks: Sequence[Hook] = (), should_cancel: Callable[[], bool] | None = None) -> dict[str, float]:
        """Step to ``cfg.iterations``, running every hook after each step. ``should_cancel`` is checked
        before every step; True raises ``TrainingCancelled`` (the caller saves the checkpoint)."""
        metrics: dict[str, float] = {}
        while self.iteration < self.cfg.iterations:
            if should_cancel is not None and should_cancel():
                raise TrainingCancelled(self.iteration)
            t0 = time.perf_counter()
            with section("step"):
                metrics = self.step()
            self.elapsed_s += time.perf_counter() - t0
            with section("hooks"):
                for hook in hooks:
                    hook(self, metrics)
        return metrics

    # -- state --

    def state_dict(self) -> dict[str, Any]:
        """Named and versioned: everything needed to continue exactly where this run is."""
        return {
            "state_version": STATE_VERSION,
            "mode": self.cfg.mode,
            "config": to_dict(self.cfg),
            "iteration": self.iteration,
            "elapsed_s": self.elapsed_s,
            "history": list(self.history),
            "gaussians": {k: v.detach().clone() for k, v in self.gaussians.items()},
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "densify": self.densifier.state_dict(),
            "rng": {
                "torch": torch.get_rng_state(),  # gsplat's split draws from it
                "views": self._view_gen.get_state(),
                "view_queue": list(self._view_queue),
            },
            "medium": self.medium.state_dict() if self.medium is not None else None,
            "exposure": self.exposure.state_dict() if self.exposure is not None else None,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if sd.get("state_version") != STATE_VERSION or sd.get("mode") != self.cfg.mode:
            raise ValueError(
                f"cannot resume: state version {sd.get('state_version')!r} mode {sd.get('mode')!r}, "
                f"expected {STATE_VERSION} / {self.cfg.mode!r}"
            )
        changed = config_changes(sd["config"], self.cfg)
        if changed:
            log.warning("resuming with a changed config; fields differing from the checkpoint: %s", changed)
        for k in GAUSSIAN_KEYS:
            self.gaussians[k] = nn.Parameter(sd["gaussians"][k].to(self.device))
        self.optimizers = make_optimizers(self.gaussians, self.cfg, self.extent)
        for k, opt in self.optimizers.items():
            opt.load_state_dict(sd["optimizers"][k])
        self.densifier.load_state_dict(sd["densify"])
        torch.set_rng_state(sd["rng"]["torch"])
        self._view_gen.set_state(sd["rng"]["views"])
        self._view_queue = list(sd["rng"]["view_queue"])
        self.iteration = int(sd["iteration"])
        self.elapsed_s = float(sd["elapsed_s"])
        self.history = list(sd["history"])
        if self.medium is not None and sd.get("medium") is not None:
            self.medium.load_state_dict(sd["medium"])
        if self.exposure is not None and sd.get("exposure") is not None:
            self.exposure.load_state_dict(sd["exposure"])

    def save(self, path: str | Path) -> Path:
        return save_checkpoint(path, self.state_dict())


def config_changes(saved: dict[str, Any], cfg: TrainConfig) -> list[str]:
    """Fields of ``cfg`` that differ from a checkpoint's saved config (all fields, including cosmetic ones)."""
    try:
        saved_cfg = to_dict(from_dict(TrainConfig, saved))  # normalises JSON/tuple differences
    except (TypeError, ValueError):  # written by another version of TrainConfig
        return sorted(set(saved) ^ set(to_dict(cfg))) or ["<unreadable>"]
    return [k for k, v in to_dict(cfg).items() if saved_cfg.get(k) != v]


def train(
    scene: Scene,
    images: Sequence[ImageLike],
    cfg: TrainConfig,
    *,
    test_views: Sequence[View] = (),
    test_images: Sequence[ImageLike] = (),
    checkpoint_dir: str | Path | None = None,
    on_progress: ProgressFn | None = None,
    should_cancel: Callable[[], bool] | None = None,
    device: torch.device | str = "cpu",
    hooks: Sequence[Hook] = (),
) -> TrainResult:
    """Train on ``scene.views`` with ``images`` (one [H, W, 3] float image in [0, 1] per view).

    With ``checkpoint_dir``: resumes from ``<dir>/<CHECKPOINT_NAME>`` (in a job, ``JobLayout.checkpoint``) when
    it was written with the same config (else starts afresh, with a warning, and overwrites it); saves it every
    ``cfg.checkpoint_every`` iterations, at the end, and before raising ``TrainingCancelled``.
    ``on_progress(iteration, total, metrics)`` runs after every step, ``should_cancel()`` before every step;
    ``hooks`` run after every step before the built-in ones (``pipeline.train.hooks``). Held-out views
    (``test_views``/``test_images``) are scored every ``cfg.eval_every`` iterations and at the end.
    """
    trainer = Trainer(scene, images, cfg, device=device)
    ckpt = Path(checkpoint_dir) / CHECKPOINT_NAME if checkpoint_dir is not None else None
    if ckpt is not None and ckpt.exists():
        saved = load_checkpoint(ckpt, map_location=trainer.device)
        changed = set(config_changes(saved.get("config", {}), cfg)) - _NON_SEMANTIC
        if changed:
            log.warning("checkpoint %s was trained with other settings (%s): starting afresh", ckpt, sorted(changed))
        else:
            trainer.load_state_dict(saved)
            log.info("resumed from %s at iteration %d", ckpt, trainer.iteration)
    hooks = [*hooks, log_hook(cfg.log_every)]
    if test_views:
        views, targets = prepare_images(test_views, test_images, cfg.downscale, trainer.device)
        hooks.append(eval_hook(cfg.eval_every, views, targets))
    if ckpt is not None:
        hooks.append(checkpoint_hook(cfg.checkpoint_every, ckpt))
    if on_progress is not None:
        hooks.append(progress_hook(on_progress))  # last, so it sees "test_psnr"
    try:
        metrics = trainer.run(hooks, should_cancel)
    except TrainingCancelled as exc:
        if ckpt is not None:
            exc.checkpoint = trainer.save(ckpt)
        else:
            log.warning("training cancelled at iteration %d without checkpoint_dir: state lost", exc.iteration)
        raise
    if ckpt is not None:
        trainer.save(ckpt)
    medium = trainer.medium.effective_coefficients() if trainer.medium is not None else {}
    exposure = trainer.exposure.record([v.name for v in trainer.views]) if trainer.exposure is not None else None
    return TrainResult(trainer.gaussians, trainer.iteration, metrics, trainer.history, ckpt, trainer.elapsed_s,
                       medium, exposure)
