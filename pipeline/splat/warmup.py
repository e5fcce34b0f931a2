"""Compile the CPU rasterizer's numba kernels into their on-disk cache ahead of the first job.

On a fresh install every kernel compiles at its first call: 70-160 s of the first job's wall time on our 2
shared cores (docs/DECISIONS.md, "Whole-job speed"), paid inside the mode probe. ``dualphys warmup`` (the
Docker image runs it at build time, as the user that owns the installed package, so the cache lands next to the
sources where every later process finds it) renders a small random scene forward and backward through the
``cpu`` backend in both render modes and every SH degree a job uses, which calls every kernel with the argument
types a job passes. Idempotent: with the cache filled it only loads it (~3 s), except ``raster_bwd``, which is
never cached and compiles in every process (3-5 s; ``_cpu_raster_kernels``' docstring).
"""

from __future__ import annotations

import logging
import time

from pipeline.splat.random_scene import random_scene
from pipeline.splat.rasterize import rasterize

log = logging.getLogger(__name__)


def compile_kernels(width: int = 64, height: int = 48, n: int = 500) -> dict[str, float]:
    """Call every rasterizer kernel once (forward and backward); returns seconds per call."""
    seconds = {}
    for sh_degree, mode in ((None, "RGB"), (3, "RGB+ED")):
        s = random_scene(n, width, height, seed=0, sh=sh_degree is not None)
        params = [p.requires_grad_(True) for p in s.params()]
        t0 = time.perf_counter()
        img, alpha, info = rasterize(*params, s.viewmats, s.Ks, width, height, sh_degree=sh_degree, backend="cpu",
                                     render_mode=mode)
        (img.sum() + alpha.sum()).backward()
        seconds[f"sh {sh_degree} {mode}"] = round(time.perf_counter() - t0, 2)
    log.info("rasterizer kernels compiled or loaded: %s", seconds)
    return seconds
