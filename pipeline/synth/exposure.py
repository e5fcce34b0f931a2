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
FALL_OFF_FILE = "fall_off.json"


def _rewrite_exposed(path: Path, log_gain) -> None:
    """Rewrite the 8-bit photo at ``path`` as a camera with gains exp(``log_gain(image)``) on linear light records
    it (broadcast over [H, W, 3]; the sensor clips at 1)."""
    img = read_image(path).astype(np.float64)
    write_image(path, np.clip(np.round(np.clip(exposed(img, log_gain(img), "srgb"), 0, 1) * 255), 0, 255)
                .astype(np.uint8))


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
        _rewrite_exposed(p, lambda img, g=g: np.log(g))
    record = {"spread": spread, "white_balance": white_balance, "space": "linear light",
              "gains": {p.name: [round(float(x), 6) for x in g] for p, g in zip(photos, gains, strict=True)}}
    (root / EXPOSURE_FILE).write_text(json.dumps(record, indent=2))
    return record


def fall_off_field(width: int, height: int, strength: float) -> np.ndarray:
    """A camera's in-frame fall-off as real survey photos show it (the AIMS lines: brighter at the bottom and on
    one side, darker towards the corners), a multiplicative field on linear light [H, W]:
    ``exp(s·(0.5 y − 0.3 x − 0.4 (x² + y²)))`` over coordinates in half-widths / half-heights from the centre,
    divided by its mean. ``strength`` s = 0.3 spans 1.7x from the darkest corner to the brightest and 1.5x over
    a 5 x 5 grid of blocks (AIMS Erub's survey mean image: 1.6x)."""
    x = (np.arange(width) + 0.5) / width * 2 - 1
    y = (np.arange(height) + 0.5) / height * 2 - 1
    X, Y = np.meshgrid(x, y)
    f = np.exp(strength * (0.5 * Y - 0.3 * X - 0.4 * (X * X + Y * Y)))
    return f / f.mean()


def fall_off_scene(root: str | Path, strength: float) -> dict:
    """Multiply every photo in ``root/images`` by :func:`fall_off_field` on linear light (the sensor clips at 1);
    ``fall_off.json`` records it. ``clean/`` stays the truth of the seabed's colours."""
    root = Path(root)
    photos = sorted(p for p in (root / "images").iterdir() if p.is_file())
    for p in photos:
        _rewrite_exposed(p, lambda img: np.log(fall_off_field(img.shape[1], img.shape[0], strength))[..., None])
    record = {"strength": strength, "field": "exp(s(0.5y - 0.3x - 0.4(x^2 + y^2))) / mean, linear light"}
    (root / FALL_OFF_FILE).write_text(json.dumps(record, indent=2))
    return record


__all__ = ["EXPOSURE_FILE", "FALL_OFF_FILE", "expose_scene", "fall_off_field", "fall_off_scene"]
