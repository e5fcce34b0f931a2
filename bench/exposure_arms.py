"""Restored J with per-frame exposure and white balance against the fixed camera, on one SfM model (issue 39).

    python bench/exposure_arms.py ROOT [--seeds 0,1,2] [--preset medium] [--mode homogeneous] [--size 320x240]
    python bench/exposure_arms.py ROOT --table      # the table of every seed finished under ROOT

For each seed: a generated photo-textured scene photographed twice, by a fixed camera ("plain") and with every
frame's exposure within ±30 % and white balance within ±10 % ("varied", :func:`pipeline.synth.exposure.expose_scene`
on the same renders). One SfM model serves both arms: the plain job runs ingest and SfM, the varied job is a copy of
it whose photos are replaced by the varied ones (and undistorted through the same model), then both run the rest of
a ``--preset fast`` job. Between two separate SfM runs a 320x240 scene's restoration moves by 2-3 dB, which hides a
0.5 dB effect of the gains; on one model what differs is the photos alone. Scored: the restored photos' PSNR against
the true clean images (restore.json ``truth``, training and held-out photos) and the gains against exposure.json.
Jobs resume (finished stages are skipped), so an interrupted run picks up where it stopped.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

import numpy as np
from shared_sfm import share_sfm

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.synth.exposure import EXPOSURE_FILE, expose_scene
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene
from pipeline.synth.water import TRUE_WATER_FILE

log = logging.getLogger("bench.exposure_arms")

SPREAD, WHITE_BALANCE = 0.3, 0.1
BEFORE_TRAIN = ("ingest", "sfm")


def make_scenes(root: Path, seed: int, preset: str, size: tuple[int, int], views: int,
                water_space: str) -> tuple[Path, Path]:
    plain, varied = root / f"scene-{seed}-plain", root / f"scene-{seed}-varied"
    if not (plain / TRUE_WATER_FILE).is_file():
        generate_photo_scene(PhotoSynthConfig(views=views, width=size[0], height=size[1], preset=preset, seed=seed,
                                              water_space=water_space),
                             plain)
    if not (varied / EXPOSURE_FILE).is_file():
        shutil.rmtree(varied, ignore_errors=True)
        shutil.copytree(plain, varied)
        expose_scene(varied, SPREAD, WHITE_BALANCE, seed=seed)
    return plain, varied


def gain_error(varied_job: Path, varied_scene: Path) -> dict:
    truth = json.loads((varied_scene / EXPOSURE_FILE).read_text())["gains"]
    exposure = json.loads(JobLayout(varied_job).train_result.read_text())["exposure"]
    trained, got = exposure["views"], exposure["photos"]
    names = sorted(got)
    lt, lg = (np.log([g[n] for n in names]) for g in (truth, got))
    on = [i for i, n in enumerate(names) if n in trained]  # the model's exposure is the training views' mean
    err = np.abs(np.expm1((lg - lg[on].mean(0)) - (lt - lt[on].mean(0))))
    return {"median": round(float(np.median(err)), 4), "worst": round(float(err.max()), 4)}


def run_seed(root: Path, seed: int, args) -> dict:
    plain_scene, varied_scene = make_scenes(root, seed, args.preset, args.size, args.views, args.water_space)
    jobs = {"plain": root / f"job-{seed}-plain", "varied": root / f"job-{seed}-varied"}

    def options(scene: Path) -> JobOptions:  # one source for both, so the shared markers stay valid
        return JobOptions(source=str(plain_scene / "images"), ground_truth=str(scene), preset="fast",
                          mode=args.mode, seed=seed)

    run_job(jobs["plain"], options(plain_scene), stages=BEFORE_TRAIN)
    share_sfm(jobs["plain"], jobs["varied"], varied_scene / "images")
    out = {"seed": seed, "preset": args.preset, "mode": args.mode, "water_space": args.water_space}
    for arm, scene in (("plain", plain_scene), ("varied", varied_scene)):
        run_job(jobs[arm], options(scene))
        truth = json.loads(JobLayout(jobs[arm]).restore_result.read_text())["truth"]
        chosen = json.loads(JobLayout(jobs[arm]).train_result.read_text()).get("mode")
        out[arm] = {"mode": chosen, **{pool: {k: round(truth[pool][k], 2) for k in ("photo_psnr", "restored_psnr")}
                                       for pool in ("train", "test")}}
    out["gain_error"] = gain_error(jobs["varied"], varied_scene)
    out["delta"] = {pool: round(out["varied"][pool]["restored_psnr"] - out["plain"][pool]["restored_psnr"], 2)
                    for pool in ("train", "test")}
    (root / f"seed-{seed}.json").write_text(json.dumps(out, indent=2))
    return out


def table(root: Path) -> str:
    rows = [json.loads(p.read_text()) for p in sorted(root.glob("seed-*.json"))]
    lines = ["| seed | mode plain / varied | restored train: plain, varied (Δ) | held-out: plain, varied (Δ) | "
             "gain error median / worst |", "|---|---|---|---|---|"]
    for r in rows:
        cells = [f"{r['plain'][p]['restored_psnr']:.2f}, {r['varied'][p]['restored_psnr']:.2f} "
                 f"({r['delta'][p]:+.2f})" for p in ("train", "test")]
        lines.append(f"| {r['seed']} | {r['plain']['mode']} / {r['varied']['mode']} | {cells[0]} | {cells[1]} | "
                     f"{100 * r['gain_error']['median']:.1f} % / {100 * r['gain_error']['worst']:.1f} % |")
    if rows:
        mean = {p: np.mean([r["delta"][p] for r in rows]) for p in ("train", "test")}
        lines.append(f"| mean of {len(rows)} | | Δ {mean['train']:+.2f} | Δ {mean['test']:+.2f} | |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--preset", default="medium", choices=["clear", "medium", "turbid"])
    ap.add_argument("--mode", default="homogeneous")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--water-space", default="linear", choices=["srgb", "linear"],
                    help="the generator's water on linear light (physical, the default) or on sRGB values")
    ap.add_argument("--table", action="store_true", help="only print the table of the seeds finished under ROOT")
    args = ap.parse_args()
    args.size = tuple(int(x) for x in args.size.split("x"))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args.root.mkdir(parents=True, exist_ok=True)
    if not args.table:
        for seed in (int(s) for s in args.seeds.split(",")):
            log.info("seed %d: %s", seed, json.dumps(run_seed(args.root, seed, args)))
    print(table(args.root))


if __name__ == "__main__":
    main()
