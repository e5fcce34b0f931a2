"""How well each backscatter cue measures the veil on generated scenes, against their truth (issue 40, item 1).

    python bench/backscatter_cues.py SCENE [SCENE ...] [--sfm-root DIR] [--json OUT]

A SCENE is a generated folder (``dualphys synth``: images/, depth/, water.json, sparse_gt/). With ``--sfm-root``,
the posed model is DIR/<scene name> (a ``dualphys sfm`` output of SCENE/images), aligned to the truth for the scale
(β in 1/m); without it the true tracks. For each scene:

- **range fit**: the sparse points' water fit (:func:`~pipeline.medium.estimate.fit_medium`, the classified water
  type's prior), its B∞ and β_B against the truth, and the veil it implies at the sightings' median range,
  B(r) = B∞(1 − e^(−β_B r)), the quantity a restoration subtracts;
- **dark pixels** (Sea-thru): the 1st percentile of each channel over the pixels of a range bin (the true depth),
  against the true B(r) of the bin; and per view at the view's median sighting range (what is known before
  training: no dense depth).

Errors are relative: (measured − truth) / truth.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import torch

from pipeline.medium.estimate import fit_medium, gather_observations
from pipeline.medium.formation import homogeneous_backscatter
from pipeline.scene.align import align_to_reference
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import ray_length_factor
from pipeline.synth.ground_truth import GroundTruth, load_ground_truth
from pipeline.train.setup import load_training_images
from pipeline.water import classify
from pipeline.water.stage import classify_pick

PERCENTILE = 1.0  # the dark-pixel cue's percentile
RANGE_BINS = 6


def veil(b_inf: np.ndarray, beta_b: np.ndarray, r: float) -> np.ndarray:
    """The veil at range ``r``, paper eq. 6 (:func:`~pipeline.medium.formation.homogeneous_backscatter`). [3]"""
    d = torch.full((1, 1, 1, 1), float(r), dtype=torch.float64)
    return homogeneous_backscatter(d, torch.as_tensor(beta_b), torch.as_tensor(b_inf)).reshape(3).numpy()


def dense_dark_pixels(gt: GroundTruth, b_inf: np.ndarray, beta_b: np.ndarray) -> list[list[float]]:
    """Per range bin of the true depth (pooled over views): the relative error of the photos' low percentile as
    the veil at the bin's median range. [bins][3]"""
    ranges, pixels = [], []
    for v in gt.scene.views:
        z = np.load(gt.root / "depth" / f"{Path(v.name).stem}.npy")
        hit = z < 999
        ranges.append((z * ray_length_factor(v.camera))[hit])
        pixels.append(srgb_to_linear(read_image(v.image_path).astype(np.float64))[hit])
    r, px = np.concatenate(ranges), np.concatenate(pixels)
    edges = np.percentile(r, np.linspace(2, 98, RANGE_BINS + 1))
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (r >= lo) & (r < hi)
        true = veil(b_inf, beta_b, float(np.median(r[sel])))
        out.append(((np.percentile(px[sel], PERCENTILE, axis=0) - true) / true).tolist())
    return out


def measure(root: Path, model_root: Path | None) -> dict:
    gt = load_ground_truth(root)
    b_inf, beta_b = np.asarray(gt.water["B_inf"]), np.asarray(gt.water["beta_B"])
    scene = load_scene(model_root) if model_root else gt.scene
    m_per_unit = align_to_reference(scene, gt.scene)["scale"] if model_root else 1.0
    tau = classify([read_image(v.image_path) for v in classify_pick(scene.views)]).settings.init_optical_depth
    images = load_training_images(scene.views, 1, "linear")
    photos = [images[i].numpy() for i in range(len(scene.views))]
    obs = gather_observations(scene.points, scene.views, photos, scene.sightings)
    est = fit_medium(obs, tau)
    if est is None:
        raise SystemExit(f"{root}: too few sightings for the water fit")
    r_med = est.median_range * m_per_unit
    fit_b_inf, fit_beta_b = np.asarray(est.B_inf), np.asarray(est.beta_B) / m_per_unit
    per_view = []
    for k, img in enumerate(photos):
        seen = obs.view == k
        if seen.sum() >= 20:
            true = veil(b_inf, beta_b, float(np.median(obs.range[seen])) * m_per_unit)
            per_view.append((np.percentile(img.reshape(-1, 3), PERCENTILE, axis=0) - true) / true)
    pv = np.asarray(per_view)
    return {
        "scene": root.name, "range_ratio": round(est.range_ratio, 3), "median_range_m": round(r_med, 3),
        "range_fit": {
            "B_inf": (fit_b_inf / b_inf - 1).round(3).tolist(), "beta_B": (fit_beta_b / beta_b - 1).round(3).tolist(),
            "veil_at_median_range": (veil(fit_b_inf, fit_beta_b, r_med) / veil(b_inf, beta_b, r_med) - 1).round(3)
            .tolist(),
            "B_inf_source": est.uncertainty["B_inf"]["source"] if est.uncertainty else None},
        "dark_pixels_dense": np.round(dense_dark_pixels(gt, b_inf, beta_b), 3).tolist(),
        "dark_pixels_per_view": {"median": np.median(pv, 0).round(3).tolist(), "std": pv.std(0).round(3).tolist()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--sfm-root", type=Path, default=None, help="posed models at DIR/<scene name>")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rows = [measure(s, args.sfm_root / s.name if args.sfm_root else None) for s in args.scenes]
    def pct(xs) -> str:
        return " / ".join(f"{100 * x:+.0f}" for x in xs)

    print("| scene | range ratio | range fit B∞ % | β_B % | B(r_med) % | dark pixels, dense (bins) % "
          "| dark pixels, per view % |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        dense = np.asarray(row["dark_pixels_dense"])
        print(f"| {row['scene']} | {row['range_ratio']:.2f} | {pct(row['range_fit']['B_inf'])} | "
              f"{pct(row['range_fit']['beta_B'])} | {pct(row['range_fit']['veil_at_median_range'])} | "
              f"{pct(np.median(dense, 0))} (bins {100 * dense.min():+.0f}..{100 * dense.max():+.0f}) | "
              f"{pct(row['dark_pixels_per_view']['median'])} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
