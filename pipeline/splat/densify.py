"""Adaptive density control: gsplat's ``DefaultStrategy`` (3DGS clone/split/prune/reset) on any device.

The strategy works on CPU tensors: it only needs the rasterizer's ``info`` (``means2d`` [C, N, 2] with its
gradient, integer ``radii`` [C, N, 2], ``width``, ``height``, ``n_cameras``) and does its optimiser surgery
with plain torch (``gsplat.strategy.ops``). No gsplat CUDA op is reached: ``ops`` imports
``quat_scale_to_covar_preci``/``compute_relocation`` but only MCMC's relocation calls them.

``_Strategy`` subclasses it for four reasons, each small:
- gsplat 1.5.3 never resets opacities: its test ``step % reset_every == 0 & step > 0`` parses as
  ``step % reset_every == (0 & step) > 0``, which is always False (upstream PR nerfstudio-project/gsplat#776,
  open). 3DGS resets every 3000 iterations, so we do too.
- ``max_gaussians``: growth stops at a cap (highest gradients first), a guard for 2-core machines.
- counts are returned and logged instead of ``print``ed, and no ``torch.cuda.empty_cache()``;
- the per-step gradient bookkeeping of one camera as masked adds (the same sums, fewer passes).

Randomness: ``split`` samples new positions from torch's global generator; the trainer seeds it and keeps its
state in checkpoints so a resumed run splits identically.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from pipeline.config import DensifyConfig

log = logging.getLogger(__name__)

DENSIFY_STATE_VERSION = 1


@dataclass
class DensifyEvent:
    """What one refinement step did."""

    iteration: int
    duplicated: int = 0
    split: int = 0
    pruned: int = 0
    opacity_reset: bool = False
    n_gaussians: int = 0


class _Fixes:
    """What ``_Strategy`` changes of gsplat's ``DefaultStrategy`` (module docstring), mixed in before it: its
    ``super()`` is DefaultStrategy. The class itself is made in :func:`_make_strategy`, where gsplat is imported."""

    max_gaussians: int  # growth stops at this many Gaussians (0 = no cap)
    reset_until: int  # no opacity reset at or after this iteration (0 = no limit)

    def step_post_backward(
        self,
        params: nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        packed: bool = False,
    ) -> DensifyEvent | None:
        """DefaultStrategy.step_post_backward with the reset condition fixed; returns what it did."""
        if step >= self.refine_stop_iter:
            return None
        self._update_state(params, state, info, packed=packed)
        event = None
        if (
            step > self.refine_start_iter
            and step % self.refine_every == 0
            and step % self.reset_every >= self.pause_refine_after_reset
        ):
            n_dupli, n_split = self._grow_gs(params, optimizers, state, step)
            n_prune = self._prune_gs(params, optimizers, state, step)
            state["grad2d"].zero_()
            state["count"].zero_()
            event = DensifyEvent(step, int(n_dupli), int(n_split), int(n_prune))
        if step % self.reset_every == 0 and step > 0 and (self.reset_until <= 0 or step < self.reset_until):
            from gsplat.strategy.ops import reset_opa  # lazy: gsplat loads with the strategy (_make_strategy)

            reset_opa(params=params, optimizers=optimizers, state=state, value=self.prune_opa * 2.0)
            event = event or DensifyEvent(step)
            event.opacity_reset = True
        if event is not None:
            event.n_gaussians = len(params["means"])
        return event

    @torch.no_grad()
    def _update_state(self, params, state, info, packed=False):  # type: ignore[no-untyped-def]
        """DefaultStrategy._update_state for one camera, as masked adds: the same sums (a Gaussian gets its
        own gradient norm or exactly 0), without the row gathers and index_add_ of the general path
        (~3 of the ~5 ms its bookkeeping took a step at 100k Gaussians). Other cases: gsplat's."""
        radii = info.get("radii")
        if packed or self.absgrad or self.refine_scale2d_stop_iter > 0 or radii is None or radii.shape[0] != 1:
            return super()._update_state(params, state, info, packed=packed)  # type: ignore[misc]
        n = len(params["means"])
        grad = info[self.key_for_gradient].grad[0]  # [N, 2]
        scale = grad.new_tensor([info["width"] / 2.0 * info["n_cameras"], info["height"] / 2.0 * info["n_cameras"]])
        sel = (radii[0] > 0.0).all(dim=-1)  # [N]
        if state["grad2d"] is None:
            state["grad2d"] = torch.zeros(n, device=grad.device)
        if state["count"] is None:
            state["count"] = torch.zeros(n, device=grad.device)
        state["grad2d"].add_(torch.where(sel, (grad * scale).norm(dim=-1), 0.0))
        state["count"].add_(sel.to(torch.float32))

    @torch.no_grad()
    def _grow_gs(self, params, optimizers, state, step):  # type: ignore[no-untyped-def]
        """DefaultStrategy._grow_gs, with growth held to ``max_gaussians``."""
        if self.max_gaussians > 0:
            room = self.max_gaussians - len(params["means"])
            if room <= 0:
                return 0, 0
            grads = state["grad2d"] / state["count"].clamp_min(1)  # [N]
            if int((grads > self.grow_grad2d).sum()) > room:
                # each clone or split adds one Gaussian: keep the `room` largest gradients
                keep = torch.zeros_like(grads, dtype=torch.bool)
                keep[grads.topk(room).indices] = True
                state["grad2d"] = torch.where(keep, state["grad2d"], torch.zeros_like(grads))
        return super()._grow_gs(params, optimizers, state, step)  # type: ignore[misc]


def _make_strategy(cfg: DensifyConfig) -> Any:
    """A configured ``_Strategy``: gsplat's DefaultStrategy with :class:`_Fixes`."""
    from gsplat.strategy import DefaultStrategy  # lazy: `import pipeline` needs only numpy and torch

    @dataclass
    class _Strategy(_Fixes, DefaultStrategy):
        max_gaussians: int = 0
        reset_until: int = 0

    return _Strategy(
        prune_opa=cfg.prune_opacity,
        grow_grad2d=cfg.grow_grad2d,
        grow_scale3d=cfg.grow_scale3d,
        prune_scale3d=cfg.prune_scale3d,
        refine_start_iter=cfg.refine_start,
        refine_stop_iter=cfg.refine_stop,
        refine_every=cfg.refine_every,
        reset_every=cfg.reset_every,
        pause_refine_after_reset=cfg.pause_after_reset,
        absgrad=False,
        verbose=False,
        max_gaussians=cfg.max_gaussians,
    )


class Densifier:
    """Holds the strategy and its running statistics; the trainer calls it around ``loss.backward()``.

    ``params`` must be the Gaussian ``ParameterDict`` alone and ``optimizers`` one single-group optimiser per
    key of it (gsplat's convention). Medium parameters never go in here.
    """

    def __init__(self, cfg: DensifyConfig, scene_scale: float) -> None:
        self.cfg = cfg
        self.strategy = _make_strategy(cfg)
        self.state: dict[str, Any] = self.strategy.initialize_state(scene_scale=float(scene_scale))

    def stop_resets_at(self, iteration: int) -> None:
        """No opacity reset at or after ``iteration``. A reset drops every Gaussian to near-transparent and relies
        on the photometric loss to bring back the ones the scene needs; in a medium mode that loss no longer
        does, because an uncovered pixel shows the water's veiling light, which in murky water is close to the
        photo already (docs/DECISIONS.md, "The water must not eat the scene")."""
        self.strategy.reset_until = int(iteration)

    def check(self, params: nn.ParameterDict, optimizers: dict[str, torch.optim.Optimizer]) -> None:
        """gsplat's sanity check (same keys, one param group each), as a ValueError."""
        try:
            self.strategy.check_sanity(params, optimizers)
        except AssertionError as exc:
            raise ValueError(f"densification cannot drive these parameters: {exc}") from exc

    def pre_backward(
        self,
        params: nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        iteration: int,
        info: dict[str, Any],
    ) -> None:
        """Before ``loss.backward()``: makes ``info['means2d']`` keep its gradient."""
        info.setdefault("gaussian_ids", None)  # gsplat asserts the key exists even when not packed
        self.strategy.step_pre_backward(params, optimizers, self.state, iteration, info)

    def post_backward(
        self,
        params: nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        iteration: int,
        info: dict[str, Any],
    ) -> DensifyEvent | None:
        """After backward (and the optimiser step): accumulate gradients; grow/prune/reset when scheduled."""
        info.setdefault("gaussian_ids", None)
        event = self.strategy.step_post_backward(params, optimizers, self.state, iteration, info, packed=False)
        if event is not None:
            log.debug("densify %s", event)
        return event

    def state_dict(self) -> dict[str, Any]:
        """Named, versioned running statistics (tensors or None) for checkpoints."""
        return {"version": DENSIFY_STATE_VERSION, **{k: v for k, v in self.state.items()}}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if sd.get("version") != DENSIFY_STATE_VERSION:
            raise ValueError(f"densify state version {sd.get('version')!r}, expected {DENSIFY_STATE_VERSION}")
        state = {k: v for k, v in sd.items() if k != "version"}
        missing = set(self.state) - set(state)
        if missing:
            raise ValueError(f"densify state lacks {sorted(missing)}")
        self.state = {k: (v.clone() if isinstance(v, Tensor) else v) for k, v in state.items()}
