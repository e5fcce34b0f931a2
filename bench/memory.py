"""Peak memory of the train stage at survey size: 100 and 300 frames at 640x480 training size.

Memory is set by the data (targets, per-view maps, Gaussians), not by the run's length, so each size runs the
whole train stage (``pipeline.train.stage.stage_train``: images read at the training size, training, the
collapse check's assessment, the held-out curve) for a few hundred iterations. The frames are made cheaply: the
procedural generator at 160x120 (supersample 1, true cameras and points, no SfM), each image upscaled 4x to
640x480 and the cameras scaled with it. Each size runs in a fresh child process; its peak RSS
(``ru_maxrss``) is reported whole and above the process's own after its imports.

    python bench/memory.py --frames 100 300 --iterations 300 --out /tmp/dualphys-memory
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

UPSCALE = 4  # generated at 160x120, trained at 640x480


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


def child(job: Path, iterations: int, mode: str) -> dict:
    """Run the train stage once in this process; its peak RSS."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    import torch  # noqa: F401  (counted in the baseline, as in a worker)

    from pipeline.job.options import JobOptions, StageContext
    from pipeline.train import stage as _stage  # noqa: F401
    from pipeline.train.setup import load_training_images  # noqa: F401

    base_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    out = _stage.stage_train(job, JobOptions(source=str(job / "scene" / "images"), mode=mode, iterations=iterations,
                                             max_width=640), StageContext())
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"train_views": out["n_train_views"], "n_gaussians": out["n_gaussians"], "iterations": out["iterations"],
            "mode": out["mode"], "seconds": round(time.perf_counter() - t0, 1),
            "peak_rss_mb": round(peak_kb / 1024), "baseline_rss_mb": round(base_kb / 1024),
            "stage_peak_mb": round((peak_kb - base_kb) / 1024)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--mode", default="dualphys")
    ap.add_argument("--out", type=Path, default=Path("/tmp/dualphys-memory"))
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child, args.iterations, args.mode)), flush=True)
        return
    for n in args.frames:
        job = args.out / f"job_{n}"
        make_scene(n, job / "scene")
        for stale in ("train",):  # a fresh train stage each time (no resume)
            import shutil

            shutil.rmtree(job / stale, ignore_errors=True)
        res = subprocess.run([sys.executable, __file__, "--child", str(job), "--iterations", str(args.iterations),
                              "--mode", args.mode], capture_output=True, text=True, check=False)
        if res.returncode != 0:
            print(json.dumps({"frames": n, "error": res.stderr.strip().splitlines()[-3:]}), flush=True)
            continue
        print(json.dumps({"frames": n, "size": "640x480", **json.loads(res.stdout.strip().splitlines()[-1])}),
              flush=True)


if __name__ == "__main__":
    main()
