"""Held-out PSNR against iterations at two survey sizes: the measurement behind the schedule rule's exponent.

The procedural generator's survey grows with its view count (a fixed 0.3 m step along the path, the world sized to
the path), so 72 views cover three times the seabed of 24 at the same overlap, as a longer real survey does.
Each size is trained with its ground-truth cameras and points (no SfM), mode ``3dgs`` (what governs the
Gaussians' convergence; the medium starts at a fixed fraction of whatever length is chosen), on the fast preset's
schedule compressed to each iteration count, and scored on the held-out views (every 8th). Prints one JSON line
per run.

    python bench/schedule.py --runs 24:3000 24:6000 72:3000 72:5196 72:9000 --size 160x120 --out /tmp/sched
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", nargs="+", default=["24:3000", "24:6000", "72:3000", "72:5196", "72:9000"],
                    help="views:iterations pairs")
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/dualphys-schedule"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import dataclasses

    from pipeline.config import SynthConfig, rescheduled, train_preset
    from pipeline.scene.loader import load_scene
    from pipeline.scene.split import split_views
    from pipeline.synth.procedural import generate_scene
    from pipeline.synth.water import TRUE_WATER_FILE
    from pipeline.train.setup import load_training_images
    from pipeline.train.trainer import train

    w, h = (int(x) for x in args.size.split("x"))
    fast = train_preset("fast")
    for run in args.runs:
        views, iterations = (int(x) for x in run.split(":"))
        root = args.out / f"scene_{views}_{args.size}_{args.seed}"
        if not (root / TRUE_WATER_FILE).exists():
            generate_scene(SynthConfig(views=views, width=w, height=h, preset="medium", seed=args.seed), root)
        scene = load_scene(root)
        train_views, test_views = split_views(scene.views)
        sub = scene.subset(train_views)
        cfg = rescheduled(fast, iterations, checkpoint_every=0, max_gaussians=fast.densify.max_gaussians)
        cfg = dataclasses.replace(cfg, mode="3dgs", log_every=10**9)
        t0 = time.perf_counter()
        res = train(sub, load_training_images(sub.views, 1), cfg, test_views=test_views,
                    test_images=load_training_images(test_views, 1))
        print(json.dumps({"views": views, "train_views": len(train_views), "iterations": iterations,
                          "passes": round(iterations / len(train_views), 1),
                          "test_psnr": round(res.metrics["test_psnr"], 3),
                          "n_gaussians": int(res.gaussians["means"].shape[0]),
                          "train_s": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
