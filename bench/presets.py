"""The presets table of docs/RESULTS.md ("Presets"): each training preset run as a whole job on one generated scene.

For every preset: generate (once) a 24-view `medium` scene, run the job (ingest → sfm → classify → train →
evaluate → export) in the requested mode, and read the report: wall time per stage, held-out PSNR with water,
restored-J PSNR against the true clean images (whole images, and over the pixels a training view saw).
Prints a markdown table; `--json` makes the last stdout line a JSON object. Long: `paper` is 30k iterations
(about an hour on 2 cores at 160x120).

    python bench/presets.py --presets fast balanced paper --size 160x120 --out /tmp/presets
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["fast", "balanced", "paper"])
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--mode", default="dualphys")
    ap.add_argument("--out", type=Path, default=Path("/tmp/dualphys-presets"))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from pipeline.config import SynthConfig
    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions
    from pipeline.job.runner import run_job
    from pipeline.synth.procedural import generate_scene
    from pipeline.synth.water import TRUE_WATER_FILE

    w, h = (int(x) for x in args.size.split("x"))
    scene = args.out / f"scene_{args.views}_{args.size}"
    if not (scene / TRUE_WATER_FILE).exists():  # not generated yet (its true water marks a generated scene)
        generate_scene(SynthConfig(views=args.views, width=w, height=h, preset="medium", seed=0), scene)
    rows = []
    for preset in args.presets:
        job = args.out / f"job_{preset}_{args.mode}"
        t0 = time.perf_counter()
        run_job(job, JobOptions(source=str(scene / "images"), preset=preset, mode=args.mode, max_width=1600))
        wall = time.perf_counter() - t0
        rep = json.loads(JobLayout(job).report_json.read_text())
        rest = rep.get("restoration") or {}
        rows.append({"preset": preset, "mode": rep["mode"], "iterations": rep["model"].get("iterations"),
                     "wall_s": round(wall, 1), "train_s": rep["timings"]["stages_s"].get("train"),
                     "test_psnr": rep["metrics"]["test"]["psnr"], "test_ssim": rep["metrics"]["test"]["ssim"],
                     "restored_psnr": (rest.get("restored") or {}).get("psnr"),
                     "restored_seen_psnr": (rest.get("seen") or {}).get("restored_psnr"),
                     "n_gaussians": rep["model"]["n_gaussians"]})
        print(json.dumps(rows[-1]), flush=True)
    print(f"\nmachine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; scene {args.views} views "
          f"{args.size}, generated `medium` water\n")
    print("| preset | iterations | job wall time | train | held-out PSNR (with water) | restored-J PSNR vs truth "
          "| restored J, seen pixels |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        rp, rs = (f"{r[k]:.1f} dB" if r[k] is not None else "n/a" for k in ("restored_psnr", "restored_seen_psnr"))
        print(f"| {r['preset']} | {r['iterations']} | {r['wall_s'] / 60:.1f} min | {(r['train_s'] or 0) / 60:.1f} min "
              f"| {r['test_psnr']:.1f} dB | {rp} | {rs} |")
    if args.json:
        print(json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()
