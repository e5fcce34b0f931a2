"""Seconds and peak memory of the survey stage (orthomosaics, DEM, GeoTIFFs) on a large generated survey.

A photo-family scene of ``--views`` frames (lawnmower lines at a nearly constant altitude, an altimeter and GPS in
EXIF) runs as a job up to the restore stage with a short training (the products' cost is set by the photos and the
grid, not by how long the model trained); then the survey stage runs alone in a fresh process, whose peak RSS
(``ru_maxrss``) and seconds are reported with the grid's size and the truth scores.

    python bench/survey_products.py --views 150 --out /tmp/dualphys-survey150
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline.job.options import JobOptions  # noqa: E402
from pipeline.job.runner import run_job  # noqa: E402
from pipeline.job.table import STAGES  # noqa: E402
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene  # noqa: E402

log = logging.getLogger("bench.survey_products")

CHILD = """
import json, resource, sys, time
from pathlib import Path
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, StageContext
from pipeline.survey.stage import stage_survey
job = Path(sys.argv[1])
opts = JobOptions.from_json(json.loads(JobLayout(job).options.read_text()))
t = time.perf_counter()
res = stage_survey(job, opts, StageContext())
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds": time.perf_counter() - t, "peak_mb": peak,
                  "grid": res.get("grid"), "truth": res.get("truth"), "scale": {k: v for k, v in res["scale"].items()
                  if k != "per_frame"}, "frame": res["frame"]}))
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=150)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    w, h = (int(v) for v in args.size.split("x"))
    scene = args.out / "scene"
    if not (scene / "images").is_dir():
        generate_photo_scene(PhotoSynthConfig(views=args.views, width=w, height=h, preset="medium", seed=0,
                                              altitude_range=(2.4, 2.6), oblique_fraction=0.0,
                                              gps_origin=(-9.5988, 143.7811)), scene)
    job = args.out / "job"
    opts = JobOptions(source=str(scene / "images"), mode="homogeneous", iterations=args.iterations,
                      colour_space="srgb")
    t0 = time.perf_counter()
    run_job(job, opts, stages=STAGES[:STAGES.index("survey")])
    log.info("job up to restore in %.0f s", time.perf_counter() - t0)
    out = subprocess.run([sys.executable, "-c", CHILD, str(job)], check=True, capture_output=True, text=True)
    result = {"views": args.views, "size": args.size, **json.loads(out.stdout.strip().splitlines()[-1])}
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
