"""The sparse points' exposure fit (each view's gains, the in-frame fall-off and the water) on posed scenes.

    python bench/exposure_fit.py MODEL [MODEL ...] [--truth SCENE ...] [--json OUT]

A MODEL is a posed scene (a ``dualphys sfm`` output, or a generated scene's folder). With ``--truth`` (one
generated scene per MODEL, ``-`` for none; ``dualphys synth`` with ``--exposure`` / ``--fall-off``) the gains are
scored against exposure.json and the water against water.json (β in 1/m through the alignment's scale). For
every scene: the gains' range, their trend along the capture order (the fitted last-over-first ratio, green)
against the photos' mean brightness's, the fall-off's span over the frame, and the water with each coefficient's
source. The images are read as a job with the default options reads them (its training size and colour space).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.job.options import JobOptions
from pipeline.medium.estimate import gather_observations
from pipeline.medium.exposure_fit import fit_with_exposure, view_prior
from pipeline.scene.align import align_to_reference
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.synth.exposure import EXPOSURE_FILE
from pipeline.synth.ground_truth import load_ground_truth
from pipeline.train.resolve import training_downscale
from pipeline.train.setup import load_training_images
from pipeline.water import classify
from pipeline.water.stage import classify_pick

log = logging.getLogger("bench.exposure_fit")


def trend(values: np.ndarray) -> float:
    """The fitted last-over-first ratio of log ``values`` [V] along their order."""
    t = np.linspace(0, 1, len(values))
    return float(np.exp(np.polyfit(t, values, 1)[0]))


def measure(model_root: Path, truth_root: Path | None) -> dict:
    scene = load_scene(model_root)
    opts = JobOptions(source=str(model_root / "images"))  # the images as a job's defaults read them
    downscale = training_downscale(opts, scene.views[0].camera.width)
    tau = classify([read_image(v.image_path) for v in classify_pick(scene.views)]).settings.init_optical_depth
    images = load_training_images(scene.views, downscale, opts.colour_space)
    photos = [images[i].numpy() for i in range(len(scene.views))]
    obs = gather_observations(scene.points, scene.views, photos, scene.sightings)
    est, lg = fit_with_exposure(obs, len(scene.views), tau, opts.colour_space)
    if est is None:
        return {"model": str(model_root), "fit": None}
    order = np.argsort([v.name for v in scene.views])
    means = view_prior(obs.view_mean, len(scene.views), opts.colour_space)
    out = {"model": str(model_root), "views": len(scene.views), "evidence": round(float(est.exposure_evidence), 1),
           "gains": [round(float(x), 3) for x in (np.exp(lg).min(), np.exp(lg).max())],
           "gain_trend_G": round(trend(lg[order, 1]), 3), "photo_trend_G": round(trend(means[order, 1]), 3),
           "field_span": est.field_span, "beta_D": np.round(est.beta_D, 4).tolist(),
           "B_inf": np.round(est.B_inf, 3).tolist(),
           "sources": (est.uncertainty or {}).get("beta_D", {}).get("source")}
    if truth_root is not None:
        gt = load_ground_truth(truth_root)
        scale = align_to_reference(scene, gt.scene)["scale"]
        out["error_pct"] = {k: np.round(100 * (np.asarray(getattr(est, k)) * (1 / scale if k != "B_inf" else 1)
                                               / np.asarray(gt.water[k]) - 1), 1).tolist()
                            for k in ("beta_D", "beta_B", "B_inf")}
        if (truth_root / EXPOSURE_FILE).exists():
            true = json.loads((truth_root / EXPOSURE_FILE).read_text())["gains"]
            t = np.log([true[Path(v.name).name] for v in scene.views])
            err = np.abs(np.expm1(lg - (t - t.mean(0))))
        else:
            err = np.abs(np.expm1(lg))
        out["gain_error"] = {"median": round(float(np.median(err)), 4), "worst": round(float(err.max()), 4)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--truth", nargs="*", default=None, help="a generated scene per model, - for none")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    truths = args.truth or ["-"] * len(args.models)
    if len(truths) != len(args.models):
        ap.error("give one --truth per model (- for none)")
    rows = [measure(m, None if t == "-" else Path(t)) for m, t in zip(args.models, truths, strict=True)]
    for r in rows:
        log.info("%s", json.dumps(r))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
