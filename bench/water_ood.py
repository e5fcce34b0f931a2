"""Calibration of the water classifier's unknown-water check (pipeline.water.ood; docs/DECISIONS.md
"Water type: unknown water").

Prints, per image set, the job-level medians the check compares with its thresholds (distance, falloff, luma,
clipped), the range of the per-frame falloff and distance, the class the classifier picks and the verdict:

- generated training-like frames (the classifier's own sampler, unseen scene seeds): where "typical" ends;
- every real set in /work/shared/data/real (ordinary daylight water: must be known), each as one job of the
  stage's 8 evenly spaced frames;
- constructed lamp-lit dark water (pipeline.synth.lamp) from real frames and from generated scenes with their
  depth, and a black and a saturated frame: must be unknown.

Calibration split: the thresholds were set on RUIE + U45 and the lamp cases built from them and from generated
seeds 2000-2002; AIMS (both reefs) and the lamp cases built from AIMS frames and from seeds 3000-3002 are the
held-out check. Run: ``python bench/water_ood.py [--real DIR]`` (~2 min on 2 cores).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.records import ray_length_factor
from pipeline.synth.lamp import GREEN_BROWN, LampSpec, lamp_lit_image, lamp_lit_photo
from pipeline.synth.procedural import make_camera, synth_views
from pipeline.synth.water import WaterParams, underwater_image
from pipeline.water import classify, load_classifier
from pipeline.water.controller import WATER_TYPES
from pipeline.water.dataset import render_clean, visible_range_scale
from pipeline.water.decision import images_to_tensor
from pipeline.water.features import image_features, resize_short_side
from pipeline.water.ood import clipped_fraction, illumination_falloff, mean_luma
from pipeline.water.sampling import camera_nuisance, sample_water, seabed_variation
from pipeline.water.stage import classify_pick
from pipeline.water.training import ClassifierTrainConfig

log = logging.getLogger("bench.water_ood")

REAL_SETS = {"RUIE A188": "ruie-A188-A206/images", "RUIE B571": "ruie-B571-B597/images",
             "U45 blue": "u45/blue", "U45 green": "u45/green", "U45 haze": "u45/haze",
             "AIMS Erub (held out)": "aims-erub-mt81/images", "AIMS Ugar (held out)": "aims-ugar-mt3a/images"}


def per_frame(images: list[np.ndarray]) -> dict[str, np.ndarray]:
    model = load_classifier()
    x = [resize_short_side(images_to_tensor(np.asarray(i, dtype=np.float32))) for i in images]
    f = torch.cat([image_features(t, resize=False) for t in x])
    with torch.no_grad():
        d = model.distance(f)
    return {"distance": d.numpy(), "falloff": torch.cat([illumination_falloff(t) for t in x]).numpy(),
            "luma": torch.cat([mean_luma(t) for t in x]).numpy(),
            "clipped": torch.cat([clipped_fraction(t) for t in x]).numpy()}


def row(name: str, images: list[np.ndarray]) -> str:
    d = classify(images)
    s, fr = d.ood, per_frame(images)
    p = d.probabilities[d.closest]
    return (f"| {name} | {len(images)} | {s['distance']:.1f} ({fr['distance'].min():.1f}-{fr['distance'].max():.1f})"
            f" | {s['falloff']:.2f} ({fr['falloff'].min():.2f}-{fr['falloff'].max():.2f}) | {s['luma']:.3f} | "
            f"{s['clipped']:.2f} | {d.closest} {p:.3f} | {'known' if d.known else 'UNKNOWN'} | "
            f"{d.confidence:.2f} |")


def random_lamp(rng: np.random.Generator) -> tuple[LampSpec, WaterParams]:
    k = rng.uniform(0.7, 1.4)  # murkier or clearer than the green-brown reference
    water = WaterParams(beta_D=tuple(k * b for b in GREEN_BROWN.beta_D),
                        beta_B=tuple(k * b for b in GREEN_BROWN.beta_B), B_inf=GREEN_BROWN.B_inf)
    lamp = LampSpec(exponent=rng.uniform(2.0, 8.0), ambient=rng.uniform(0.1, 0.2),
                    target_luma=rng.uniform(0.12, 0.35))
    return lamp, water


def lamp_from_photos(images: list[np.ndarray], rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for img in images:
        lamp, water = random_lamp(rng)
        out.append(lamp_lit_photo(img, rng.uniform(0.6, 2.5), rng.uniform(60.0, 100.0), rng, water, lamp))
    return out


def lamp_from_scenes(seeds: tuple[int, ...], rng: np.random.Generator, size=(160, 120)) -> list[np.ndarray]:
    out = []
    for s in seeds:
        cfg = SynthConfig(views=4, width=size[0], height=size[1], preset="none", seed=s,
                          altitude=float(rng.uniform(0.8, 2.5)), supersample=1, noise_std=0.0)
        ray = ray_length_factor(make_camera(cfg))
        for sv in synth_views(cfg)[1]:
            lamp, water = random_lamp(rng)
            out.append(lamp_lit_image(sv.J, sv.depth * ray, 1.0 / ray, rng, water, lamp))
    return out


def training_like(seeds: tuple[int, ...], rng: np.random.Generator) -> list[np.ndarray]:
    """Frames from the classifier's own sampler (water per class, camera nuisances) on unseen scene seeds."""
    cfg = ClassifierTrainConfig()
    out = []
    for v in render_clean(seeds, cfg.render):
        for wt in WATER_TYPES:
            for _ in range(2):
                water = sample_water(wt, rng)
                r = v.r * visible_range_scale(water.beta_D[1], v.r, cfg.render.optical_depth_range)
                out.append(camera_nuisance(underwater_image(seabed_variation(v.J, rng), r, water), rng))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", type=Path, default=Path("/work/shared/data/real"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    rng = np.random.default_rng(0)
    lines = ["| set | frames | distance (frames) | falloff (frames) | luma | clipped | closest, p | verdict | "
             "confidence |", "|---|---|---|---|---|---|---|---|---|"]
    gen = training_like(tuple(range(2000, 2006)), rng)
    fr = per_frame(gen)
    lines.append(f"| generated, training sampler ({len(gen)} frames): q01/q99 | | "
                 f"{np.quantile(fr['distance'], 0.99):.1f} (q99) | {np.quantile(fr['falloff'], 0.99):.2f} (q99) | "
                 f"{np.quantile(fr['luma'], 0.01):.3f} (q01) | {np.quantile(fr['clipped'], 0.99):.2f} (q99) | | | |")
    photos = {}
    for name, sub in REAL_SETS.items():
        paths = sorted(p for p in (args.real / sub).iterdir() if p.is_file())
        photos[name] = [read_image(p) for p in classify_pick(paths)]
        lines.append(row(name, photos[name]))
    for name in REAL_SETS:
        small = [resize_short_side(images_to_tensor(p))[0].permute(1, 2, 0).numpy() for p in photos[name]]
        lines.append(row(f"lamp-lit {name}", lamp_from_photos(small, rng)))
    lines.append(row("lamp-lit generated seeds 2000-2002", lamp_from_scenes((2000, 2001, 2002), rng)))
    lines.append(row("lamp-lit generated seeds 3000-3002 (held out)", lamp_from_scenes((3000, 3001, 3002), rng)))
    # the reported failure, reproduced: lamp-lit RUIE frames at 1 m, 90° lens, little daylight -> "clear"
    close = [lamp_lit_photo(resize_short_side(images_to_tensor(p))[0].permute(1, 2, 0).numpy(), 1.0, 90.0, rng,
                            lamp=LampSpec(ambient=0.05)) for p in photos["RUIE A188"]]
    lines.append(row("lamp-lit RUIE A188 at 1 m, 90°, ambient 0.05", close))
    lines.append(row("black frame", [np.zeros((120, 160, 3), np.float32)]))
    lines.append(row("saturated frame", [np.ones((120, 160, 3), np.float32)]))
    dark = [p * 0.05 for p in photos["RUIE A188"]]
    lines.append(row("RUIE A188 × 0.05 (no lamp)", dark))
    print("\n".join(lines))  # noqa: T201 - the bench's table


if __name__ == "__main__":
    main()
