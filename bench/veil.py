"""The veil left on restored photos of narrow-range surveys, against a 3DGS of the same scene without water (issue 40).

    python bench/veil.py ROOT [--presets turbid,medium] [--seeds 0,1] [--mode auto] [--altitude 2.4,2.6]
    python bench/veil.py ROOT --table       # the table of every scene finished under ROOT

For each water preset and seed: a generated photo-textured survey at nearly constant range (every view 2.4-2.6 m
above the seabed, no oblique pass, the water on linear light) and the same survey without water (the generator
draws the same seabed, path and noise for any preset). One SfM model, made from the photos with water, serves
both (:mod:`shared_sfm`); a ``--preset fast`` job runs on each: ``--mode`` (default auto) with water, 3dgs
without. Scored the same way for both, at the held-out views' true cameras (evaluate.json ``restoration``): the
model's J against the true clean image (PSNR, and the mean error per channel per view: the veil's bias), with the
photos' PSNR and, for the job with water, its restored 8-bit files (restore.json ``truth``) and the fitted B∞ and
β_B against the truth (β in 1/m through the alignment's scale).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from shared_sfm import share_sfm

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene
from pipeline.synth.water import TRUE_WATER_FILE

log = logging.getLogger("bench.veil")


def scene(root: Path, preset: str, seed: int, altitude: tuple[float, float], size: tuple[int, int]) -> Path:
    out = root / f"scene-{preset}-{seed}"
    if not (out / TRUE_WATER_FILE).is_file():
        generate_photo_scene(PhotoSynthConfig(views=24, width=size[0], height=size[1], preset=preset, seed=seed,
                                              altitude_range=altitude, oblique_fraction=0.0, water_space="linear"),
                             out)
    return out


def scores(job: Path) -> dict:
    lay = JobLayout(job)
    ev = json.loads(lay.evaluate.read_text())["restoration"]
    bias = np.array([v["bias"] for v in ev["per_view"]])
    out = {"mode": json.loads(lay.train_result.read_text())["mode"],
           "J_psnr": round(ev["restored"]["psnr"], 2), "photo_psnr": round(ev["input"]["psnr"], 2),
           "bias_mean": np.round(bias.mean(0), 3).tolist(), "bias_worst": round(float(np.abs(bias).max()), 3)}
    if ev.get("coefficients"):
        out["B_inf_error"] = ev["coefficients"]["B_inf"]
        out["beta_B_error"] = ev["coefficients"]["beta_B"]
    if lay.restore_result.is_file() and "truth" in (rr := json.loads(lay.restore_result.read_text())):
        out["restored_files_psnr"] = round(rr["truth"]["test"]["restored_psnr"], 2)
    return out


def run_one(root: Path, preset: str, seed: int, args) -> dict:
    wet, dry = (scene(root, p, seed, args.altitude, args.size) for p in (preset, "none"))
    jobs = {"water": root / f"job-{preset}-{seed}", "none": root / f"job-{preset}-{seed}-none"}

    def options(truth: Path, mode: str) -> JobOptions:  # one source for both: the shared markers stay valid
        return JobOptions(source=str(wet / "images"), ground_truth=str(truth), preset="fast", mode=mode, seed=seed)

    run_job(jobs["water"], options(wet, args.mode), stages=("ingest", "sfm"))
    share_sfm(jobs["water"], jobs["none"], dry / "images")
    run_job(jobs["water"], options(wet, args.mode))
    run_job(jobs["none"], options(dry, "3dgs"))
    out = {"preset": preset, "seed": seed, "water": scores(jobs["water"]), "none": scores(jobs["none"])}
    out["gap_db"] = round(out["none"]["J_psnr"] - out["water"]["J_psnr"], 2)
    (root / f"{preset}-{seed}.json").write_text(json.dumps(out, indent=2))
    return out


def _rgb(x) -> str:
    return " / ".join(f"{v:+.3f}" if isinstance(v, float) else str(v) for v in x)


def table(root: Path) -> str:
    rows = [json.loads(p.read_text()) for p in sorted(root.glob("*-*.json"))]
    lines = ["| scene | mode | photos | restored J (files) | 3DGS without water | gap | bias R / G / B (worst view) | "
             "B∞ error | β_B error |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r["water"]
        err = {k: _rgb((np.array(w[k]["estimated"]) / np.array(w[k]["true"]) - 1).round(2).tolist())
               if k in w else "—" for k in ("B_inf_error", "beta_B_error")}
        lines.append(f"| {r['preset']} s{r['seed']} | {w['mode']} | {w['photo_psnr']:.2f} | {w['J_psnr']:.2f} "
                     f"({w.get('restored_files_psnr', '—')}) | {r['none']['J_psnr']:.2f} | {r['gap_db']:+.2f} | "
                     f"{_rgb(w['bias_mean'])} ({w['bias_worst']:.3f}) | {err['B_inf_error']} | "
                     f"{err['beta_B_error']} |")
    return "\n".join(lines)


def _pair(text: str, cast=float) -> tuple:
    return tuple(cast(x) for x in text.replace("x", ",").split(","))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--presets", default="turbid,medium")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--mode", default="auto")
    ap.add_argument("--altitude", default="2.4,2.6", help="MIN,MAX metres above the seabed")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--table", action="store_true", help="only print the table of the scenes finished under ROOT")
    args = ap.parse_args()
    args.altitude, args.size = _pair(args.altitude), _pair(args.size, int)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args.root.mkdir(parents=True, exist_ok=True)
    if not args.table:
        for preset in args.presets.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                log.info("%s s%d: %s", preset, seed, json.dumps(run_one(args.root, preset, seed, args)))
    print(table(args.root))


if __name__ == "__main__":
    main()
