"""Cost of a full DualPhys training step against a plain 3DGS step, in the same run (issue 4: ≤ 1.5x).

Both trainers see the same generated scene (320x240 by default) and warm up first; then, interleaved, each
times the same number of steps with the medium switched on for the DualPhys trainer. Prints a table and,
with --json, a JSON object as the last stdout line:
    {"ratio_dualphys_over_3dgs": float, "step_s_3dgs": float, "step_s_dualphys": float, ...}
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _time_steps(trainer, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        trainer.step()
    return (time.perf_counter() - t0) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--gaussians", type=int, default=50_000, help="random-initialised Gaussians (0: scene points)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))

    import torch

    from pipeline.config import DensifyConfig, MediumConfig, SynthConfig, TrainConfig
    from pipeline.scene.images import read_image
    from pipeline.scene.loader import load_scene
    from pipeline.synth.procedural import generate_scene
    from pipeline.train.trainer import Trainer

    with tempfile.TemporaryDirectory() as tmp:
        root = generate_scene(SynthConfig(views=args.views, width=w, height=h, preset="medium", seed=0), tmp)
        scene = load_scene(root)
        images = [read_image(root / "images" / v.name) for v in scene.views]
    if args.gaussians:  # no points: both trainers draw the same random cloud (same seed)
        scene = type(scene)(scene.views, root=scene.root)
    no_densify = DensifyConfig(refine_start=10**9, refine_stop=10**9)  # fixed Gaussian count: same work
    total = 10**6
    common = dict(iterations=total, backend="cpu", log_every=0, densify=no_densify,
                  random_init_points=args.gaussians or 20_000)
    # Same SH degree (1, the medium modes' cap) on both sides, so the ratio is the medium's own cost.
    plain = Trainer(scene, images, TrainConfig(mode="3dgs", sh_degree=1, **common))
    dual = Trainer(scene, images, TrainConfig(mode="dualphys", medium=MediumConfig(start_fraction=0.0), **common))
    for t in (plain, dual):
        t.iteration = 2000  # past SH warm-up: both render their final degree (1)
        _time_steps(t, 3)
    rows = {"3dgs": [], "dualphys": []}
    for _ in range(args.rounds):
        rows["3dgs"].append(_time_steps(plain, args.steps))
        rows["dualphys"].append(_time_steps(dual, args.steps))
    a, b = statistics.median(rows["3dgs"]), statistics.median(rows["dualphys"])
    n = int(plain.gaussians["means"].shape[0])
    print(f"{w}x{h}, {n} Gaussians, {args.steps} steps x {args.rounds} rounds, torch threads {torch.get_num_threads()}")
    print(f"3dgs step     {a * 1000:8.1f} ms   (rounds: {', '.join(f'{x * 1000:.1f}' for x in rows['3dgs'])})")
    print(f"dualphys step {b * 1000:8.1f} ms   (rounds: {', '.join(f'{x * 1000:.1f}' for x in rows['dualphys'])})")
    print(f"ratio         {b / a:8.2f}x")
    if args.json:
        print(json.dumps({"ratio_dualphys_over_3dgs": b / a, "step_s_3dgs": a, "step_s_dualphys": b,
                          "n_gaussians": n, "size": args.size}))


if __name__ == "__main__":
    main()
