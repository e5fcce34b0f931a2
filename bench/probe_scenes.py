"""What ``--mode auto`` chooses on posed scenes, without the rest of a job: the classifier, the sparse-point water
fit and the mode probe (``pipeline.train.probe``) on each scene folder, as a table.

    python bench/probe_scenes.py SCENE [SCENE ...] [--json OUT]

A SCENE is a posed folder (images/ + a COLMAP model: a generated scene's sparse_gt/, a job's scene/, an
``dualphys sfm`` output). The split, the training size and the configs are the job's (fast preset). Used to
calibrate the probe on scenes with and without water (docs/DECISIONS.md, "Automatic mode").
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

from pipeline.job.options import JobOptions
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.split import split_views
from pipeline.train.probe import select_for_job
from pipeline.train.resolve import resolve_train_config, training_downscale
from pipeline.train.setup import load_training_images
from pipeline.water import classify
from pipeline.water.stage import classify_pick

log = logging.getLogger("bench.probe_scenes")


def probe_scene(root: Path) -> dict:
    t0 = time.perf_counter()
    scene = load_scene(root, workdir=Path(tempfile.mkdtemp(prefix="probe-undist-")))
    views = scene.views
    water = classify([read_image(v.image_path) for v in classify_pick(views)]).to_dict()
    train_views, _ = split_views(views)
    train_scene = scene.subset(train_views)
    opts = JobOptions(source=str(root), preset="fast")
    down = training_downscale(opts, views[0].camera.width)
    images = load_training_images(train_scene.views, down, opts.colour_space)
    base = resolve_train_config(opts, train_scene.views[0].camera.width, water, None, len(views))
    with tempfile.TemporaryDirectory() as out:
        sel = select_for_job(Path(out), train_scene, images, base, water=water)
    probe = sel.get("probe", {})
    homog = probe.get("homogeneous", {})
    kind = water["water_type"]
    return {"scene": str(root), "water_type": kind, "p": round(water["probabilities"].get(kind, float("nan")), 3),
            "known": water.get("known"), "chosen": sel["chosen"],
            "psnr": {m: round(s["psnr"], 2) for m, s in probe.items()},
            "learned": homog.get("effect"), "measured": homog.get("measured_effect"),
            "measurement": homog.get("measurement"), "reason": sel["reason"],
            "scored_alpha": sel.get("probe_setup", {}).get("scored_alpha"),
            "drift": (sel.get("drift") or {}).get("score"), "drift_defined": (sel.get("drift") or {}).get("defined"),
            "covered": {m: s.get("covered") for m, s in probe.items()},
            "seconds": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    for root in args.scenes:
        r = probe_scene(root)
        rows.append(r)
        log.warning("%s: %s (%s p %.2f; psnr %s; learned %s measured %s [%s]; photos' drift %s) %.0f s", root,
                    r["chosen"], r["water_type"], r["p"], r["psnr"], r["learned"], r["measured"], r["measurement"],
                    r["drift"], r["seconds"])
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
