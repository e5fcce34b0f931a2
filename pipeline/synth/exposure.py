"""Per-frame exposure and white balance applied to a generated scene's photos, with the truth kept.

Each photo in ``images/`` gets gains g_v = e_v · w_v on linear light (:mod:`pipeline.scene.exposure`): one exposure
factor e_v drawn uniformly within ±``spread`` and a white balance w_v per channel within ±``white_balance``, as an
auto-exposing camera or a towed camera's changing gain makes them; the sensor clips at 1. The gains are made
mean-neutral (geometric mean 1 per channel over the views), the only set a job can recover (it sees the ratios
between frames), so ``clean/`` stays the truth of the restored photos; ``exposure.json`` keeps them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.scene.exposure import exposed, mean_neutral
from pipeline.scene.images import read_image, write_image

EXPOSURE_FILE = "exposure.json"


def expose_scene(root: str | Path, spread: float, white_balance: float = 0.0, seed: int = 0) -> dict:
    """Apply random per-frame gains to ``root/images`` (module docstring); returns what ``exposure.json`` holds."""
    if not 0 <= spread < 1 or not 0 <= white_balance < 1:
        raise ValueError(f"exposure spread and white balance must be in [0, 1), got {spread}, {white_balance}")
    root = Path(root)
    photos = sorted(p for p in (root / "images").iterdir() if p.is_file())
    rng = np.random.default_rng(seed + 7919)
    e = rng.uniform(1 - spread, 1 + spread, size=(len(photos), 1))
    w = rng.uniform(1 - white_balance, 1 + white_balance, size=(len(photos), 3))
    gains = np.exp(mean_neutral(np.log(e * w)))  # mean-neutral: clean/ stays the truth of the restored photos
    for p, g in zip(photos, gains, strict=True):
        img = read_image(p).astype(np.float64)
        write_image(p, np.clip(np.round(np.clip(exposed(img, np.log(g), "srgb"), 0, 1) * 255), 0, 255)
                    .astype(np.uint8))
    record = {"spread": spread, "white_balance": white_balance, "space": "linear light",
              "gains": {p.name: [round(float(x), 6) for x in g] for p, g in zip(photos, gains, strict=True)}}
    (root / EXPOSURE_FILE).write_text(json.dumps(record, indent=2))
    return record


__all__ = ["EXPOSURE_FILE", "expose_scene"]
