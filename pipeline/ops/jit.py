"""Compiled loss graphs: ``torch.compile`` for the training step's losses, with the eager functions as their twins.

A medium step's losses (eq. 13's terms, the medium's own maps, SSIM) are some 150 small element-wise torch ops on
the view's images; eager torch runs each as its own pass over memory, so at 320x240 they cost more than the
rasterizer (docs/DECISIONS.md, "Whole-job speed"). ``torch.compile`` (inductor: C++ with OpenMP on the CPU) fuses
them into a few loops, forward and backward. The functions compiled are the eager ones, unchanged: a test holds
the compiled against the eager forward and backward.

When (``TrainConfig.compile_losses``): ``"auto"`` compiles a run of at least :data:`MIN_ITERATIONS` iterations when
a C++ compiler is on the PATH (the compile costs ~1-2 s per graph from inductor's on-disk cache, ~1 min on an
empty one: a short run, a test or the mode probe, does not repay it); ``"on"`` always, ``"off"`` never.

Shapes: a graph is compiled for the job's image size (one camera, one size), with the sizes callers mark
dynamic (:func:`dynamic_rows`: each view's count of sparse-point pixels) left symbolic, so every view shares
one graph; another image size is another graph (and another cache entry). Symbolic image sizes would serve every
size from one entry (and let ``dualphys warmup`` fill it), but inductor (torch 2.13) fails to lower our graphs
with them ("cannot determine truth value of Relational: 1 < s24" at the unsqueezed single-channel maps and in
SSIM's permuted convolution input; 24x32 views failed, 319x239 did not). A compile that fails falls back to the
eager function, once, with a warning: the losses are pure, so the failed call is simply run again eagerly.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable
from typing import Any, TypeVar

import torch
from torch.utils._pytree import tree_leaves

log = logging.getLogger(__name__)

MIN_ITERATIONS = 2000  # "auto" compiles runs at least this long: the presets (fast 3,000) and surveys, not tests
CompileMode = str  # "auto" | "on" | "off"
F = TypeVar("F", bound=Callable[..., Any])


def compiler_available() -> bool:
    """Whether inductor can build CPU kernels here: a C++ compiler on the PATH (torch's own check is lazy, and
    would fail inside the first training step instead)."""
    return any(shutil.which(cc) for cc in ("g++", "c++", "clang++"))


def should_compile(mode: CompileMode, iterations: int) -> bool:
    """The rule of the module docstring."""
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"compile_losses must be 'auto', 'on' or 'off', got {mode!r}")
    if mode == "off":
        return False
    if not compiler_available():
        if mode == "on":
            log.warning("compile_losses='on' but no C++ compiler is on the PATH: the losses run eagerly")
        return False
    return mode == "on" or iterations >= MIN_ITERATIONS


class Compiled:
    """``fn`` compiled on first call (static sizes but those marked by :func:`dynamic_rows`), falling back to
    ``fn`` itself for good if compiling fails.

    Nothing is compiled until the first call. That call first runs the compiled graph forward and backward
    (:func:`_trial`): the backward graph compiles lazily, and a failure there would otherwise surface in the
    training step's ``backward()``, out of reach of the fallback."""

    def __init__(self, fn: Callable[..., Any], backend: str | Callable[..., Any] = "inductor") -> None:
        self.eager = fn
        self.backend = backend  # torch.compile's backend (a test passes one that fails)
        self._compiled: Callable[..., Any] | None = None
        self.failed: str | None = None  # why compiling failed, when it did

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.failed is not None:
            return self.eager(*args, **kwargs)
        try:
            if self._compiled is None:
                # lazy: dynamo and inductor add ~1 s to import; only a compiled run needs them
                import torch._dynamo.config
                import torch._inductor.config

                # compile in this process: inductor's worker pool would fork from a Celery worker's daemonic child
                torch._inductor.config.compile_threads = 1
                # only the sizes marked by dynamic_rows vary; any other new size is a new static graph, never an
                # automatically dynamic one (inductor fails on those: module docstring)
                torch._dynamo.config.automatic_dynamic_shapes = False
                compiled = torch.compile(self.eager, backend=self.backend)
                _trial(compiled, args, kwargs)
                self._compiled = compiled
            return self._compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001  a compiler failure of any kind: the eager twin is always right
            self.failed = f"{type(exc).__name__}: {exc}"[:500]
            log.warning("torch.compile failed for %s; running it eagerly from now on (%s)",
                        getattr(self.eager, "__qualname__", self.eager), self.failed)
            return self.eager(*args, **kwargs)


def _trial(compiled: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    """Forward and backward of ``compiled`` on the call's own arguments, the backward by ``torch.autograd.grad``
    with respect to the tensor arguments only: no parameter's or tensor's ``.grad`` changes, and the autograd
    engine stops at those tensors (a render's own backward does not run). The result is thrown away."""
    inputs = [x for x in tree_leaves((args, kwargs)) if isinstance(x, torch.Tensor) and x.requires_grad]
    outs = [y for y in tree_leaves(compiled(*args, **kwargs)) if isinstance(y, torch.Tensor) and y.requires_grad]
    if inputs and outs:
        torch.autograd.grad(sum(y.sum() for y in outs), inputs, allow_unused=True)


def dynamic_rows(t: Any) -> Any:
    """``t`` with its first dimension marked as varying between calls (no recompile per size); returns ``t``."""
    import torch._dynamo  # lazy: dynamo and inductor add ~1 s to import; only a compiled run needs them

    torch._dynamo.maybe_mark_dynamic(t, 0)
    return t


def maybe_compiled(fn: F, enabled: bool) -> F:
    """``fn`` wrapped in :class:`Compiled` when ``enabled``, else ``fn`` itself."""
    return Compiled(fn) if enabled else fn  # type: ignore[return-value]
