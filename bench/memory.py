"""Peak memory of the train stage at survey size: 100 and 300 frames at 640x480 training size.

Memory is set by the data (targets, per-view maps, Gaussians), not by the run's length, so each size runs the
whole train stage (``pipeline.train.stage.stage_train``: images read at the training size, training, the
collapse check's assessment, the held-out curve) for a few hundred iterations. The frames are made cheaply: the
procedural generator at 160x120 (supersample 1, true cameras and points, no SfM), each image upscaled 4x to
640x480 and the cameras scaled with it. Each size runs in a fresh child process; its peak RSS
(``ru_maxrss``) is reported whole and above the process's own after its imports.

A few hundred iterations grow only ~10k Gaussians, while a real run at survey size grows to the survey's cap
(fast at 300 frames: 1.25M), and the Gaussians (parameters, Adam state, gradients, the rasterizer's per-Gaussian
and per-intersection buffers) are the part of the peak that grows with them. ``--gaussians budget`` (or a
number) starts training from that many Gaussians instead, so every step of the real train stage carries them:
the initial Gaussians from the scene's points, each split into ``k`` copies jittered within its own footprint,
each copy's scale shrunk by ``k^(1/3)`` (the same volume filled, as densification's splits do). The sparse
points, tracks and targets stay the scene's own. ``budget`` is the run's own cap, resolved as the train stage
resolves it (``pipeline.train.resolve``); the count reached is reported.

    python bench/memory.py --frames 100 300 --iterations 300 --out /tmp/dualphys-memory
    python bench/memory.py --frames 300 --iterations 60 --gaussians budget
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

UPSCALE = 4  # generated at 160x120, trained at 640x480

log = logging.getLogger("bench.memory")


def make_scene(frames: int, root: Path) -> Path:
    """A posed scene folder (images/ + sparse_gt/) of ``frames`` 640x480 frames, made at 160x120 and upscaled."""
    import numpy as np

    from pipeline.config import SynthConfig
    from pipeline.scene.images import read_image, write_image
    from pipeline.synth.procedural import generate_scene

    done = root / "images" / ".upscaled"
    if done.exists():
        return root
    generate_scene(SynthConfig(views=frames, width=160, height=120, supersample=1, preset="medium", seed=0), root)
    for p in sorted((root / "images").iterdir()):
        img = read_image(p)
        write_image(p, np.repeat(np.repeat(img, UPSCALE, axis=0), UPSCALE, axis=1), bits=8)
    cams = root / "sparse_gt" / "cameras.txt"
    lines = []
    for line in cams.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            lines.append(line)
            continue
        cid, model, w, h, *params = line.split()
        assert model == "PINHOLE", model
        lines.append(" ".join([cid, model, str(int(w) * UPSCALE), str(int(h) * UPSCALE),
                               *(repr(float(x) * UPSCALE) for x in params)]))
    cams.write_text("\n".join(lines) + "\n")
    for extra in ("clean", "depth"):  # not read by the train stage
        import shutil

        shutil.rmtree(root / extra, ignore_errors=True)
    done.touch()
    return root


def run_budget(job: Path, opts) -> int:
    """The Gaussian cap the train stage resolves for this job (``pipeline.train.stage.stage_train``'s way)."""
    from pipeline.scene.loader import load_scene
    from pipeline.train.resolve import resolve_train_config

    scene = load_scene(job / "scene")
    return resolve_train_config(opts, scene.views[0].camera.width, None, None, len(scene.views)).densify.max_gaussians


def replicated(params, n: int, seed: int = 0):
    """``params`` (a ParameterDict of Gaussians) grown to ``n`` by splitting each into copies: a copy's mean
    is drawn from its parent's Gaussian, its scale is the parent's / k^(1/3) for k copies, so the copies fill
    the parent's volume (screen footprints, and so the rasterizer's intersections, stay those of a denser
    cloud, not of n large blobs stacked on each other). Opacity, rotation and colour are the parent's."""
    import math

    import torch

    from pipeline.splat.gaussians import make_gaussians

    m = params["means"].shape[0]
    if n <= m:
        return params
    gen = torch.Generator().manual_seed(seed)
    parent = torch.arange(m).repeat(n // m + 1)[:n]  # every Gaussian at least once, the first n % m once more
    k = torch.bincount(parent, minlength=m).to(torch.float32)[parent]  # copies per parent  [n]
    with torch.no_grad():
        sigma = params["scales"].exp()[parent]  # [n, 3] the parent's std. dev. (identity rotation at init)
        means = params["means"][parent] + torch.randn(n, 3, generator=gen) * sigma
        log_scales = params["scales"][parent] - torch.log(k)[:, None] / 3.0
        log.info("replicated %d initial Gaussians into %d (%.1f copies each, scale / %.2f)", m, n, n / m,
                 math.pow(n / m, 1 / 3))
        return make_gaussians(means, log_scales, params["quats"][parent], params["opacities"][parent],
                              params["sh0"][parent], params["shN"][parent])


def start_with(n: int) -> None:
    """Make the trainer start from ``n`` Gaussians (``replicated``) in this process: the bench's child only."""
    from pipeline.train import trainer

    original = trainer.initial_gaussians

    def initial_gaussians(scene, cfg, extent, device):
        return replicated(original(scene, cfg, extent, device), n, cfg.seed).to(device)

    trainer.initial_gaussians = initial_gaussians  # the trainer's own name for it (imported from setup)


def gaussians_target(spec: str | None, job: Path, opts) -> int | None:
    """``--gaussians``: None (train from the scene's points, the default), ``budget`` or a number."""
    if spec is None:
        return None
    return run_budget(job, opts) if spec == "budget" else int(spec)


def child(job: Path, iterations: int, mode: str, gaussians: str | None = None) -> dict:
    """Run the train stage once in this process; its peak RSS."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    import torch  # noqa: F401  (counted in the baseline, as in a worker)

    from pipeline.job.options import JobOptions, StageContext
    from pipeline.train import stage as _stage  # noqa: F401
    from pipeline.train.setup import load_training_images  # noqa: F401

    opts = JobOptions(source=str(job / "scene" / "images"), mode=mode, iterations=iterations, max_width=640)
    target = gaussians_target(gaussians, job, opts)
    if target is not None:
        log.setLevel(logging.INFO)  # the replication's line (the parent shows this child's log as it runs)
        start_with(target)
    base_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    out = _stage.stage_train(job, opts, StageContext())
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    res = {"train_views": out["n_train_views"], "n_gaussians": out["n_gaussians"], "iterations": out["iterations"],
           "mode": out["mode"], "seconds": round(time.perf_counter() - t0, 1),
           "peak_rss_mb": round(peak_kb / 1024), "baseline_rss_mb": round(base_kb / 1024),
           "stage_peak_mb": round((peak_kb - base_kb) / 1024)}
    if target is not None:  # trained from ``target``; at the cap growth stops, so only pruning changes the count
        res.update(start_gaussians=target, budget=out["schedule"]["max_gaussians"])
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--mode", default="dualphys")
    ap.add_argument("--gaussians", default=None, metavar="budget|N",
                    help="start training from this many Gaussians (budget: the run's own cap); default: the "
                         "scene's points, as a job does")
    ap.add_argument("--out", type=Path, default=Path("/tmp/dualphys-memory"))
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child, args.iterations, args.mode, args.gaussians)), flush=True)
        return
    for n in args.frames:
        job = args.out / f"job_{n}"
        make_scene(n, job / "scene")
        for stale in ("train",):  # a fresh train stage each time (no resume)
            import shutil

            shutil.rmtree(job / stale, ignore_errors=True)
        cmd = [sys.executable, __file__, "--child", str(job), "--iterations", str(args.iterations), "--mode", args.mode]
        if args.gaussians is not None:
            cmd += ["--gaussians", args.gaussians]
        # with --gaussians the child runs long: its log goes straight to our stderr (default: kept for errors)
        stream = args.gaussians is not None
        res = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=None if stream else subprocess.PIPE, text=True,
                             check=False)
        if res.returncode != 0:
            tail = ["(the child's log is above)"] if stream else res.stderr.strip().splitlines()[-3:]
            print(json.dumps({"frames": n, "error": tail}), flush=True)
            continue
        print(json.dumps({"frames": n, "size": "640x480", **json.loads(res.stdout.strip().splitlines()[-1])}),
              flush=True)


if __name__ == "__main__":
    main()
