"""The true seabed of a generated photo-family scene at any world x, y: what a perfect DEM and a perfect nadir
orthophoto of the de-watered seabed show (issue 42's survey products are scored against it).

- height: the heightfield z(x, y) in metres (world z up), bilinear between grid nodes exactly as the renderer
  intersects it (:func:`pipeline.synth.photo_world.bilinear` of the float32 packed grid);
- colour: the clean radiance J the generator's clean/ images hold, albedo · (ambient + (1 − ambient) · lambert)
  (:func:`pipeline.synth.photo.surface_colour`), float in [0, 1] in clean/'s encoding (sRGB values: a point's J
  is the same in both water spaces, encode(decode(J)) = J). Lambertian, so it does not depend on the view.

World: metres, z up, x east, y north (:mod:`.geo` places it on the Earth). The world is rebuilt from the
generator config in the scene's water.json (``generator``): about 0.6 s for the default 1024² grid (reads the
texture photos). Use :func:`load_surface_truth` once and call :meth:`SurfaceTruth.at` many times, or the one-shot
:func:`true_surface`. A cell average (``cell``) box-filters sub-samples as a camera pixel does: heights and, for a
"linear" water-space scene, colours in linear light (re-encoded), else colours as encoded.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.config import from_dict
from pipeline.scene.colour import linear_to_srgb, srgb_to_linear
from pipeline.synth.photo import PhotoSynthConfig, PhotoWorld, build_world, surface_colour
from pipeline.synth.photo_world import bilinear
from pipeline.synth.water import TRUE_WATER_FILE

F64 = torch.float64
CHUNK = 1 << 18  # points evaluated at once (bounded memory for large grids)


def scene_config(scene_dir: str | Path) -> PhotoSynthConfig:
    """The generator config a photo-family scene was made with (its water.json ``generator``)."""
    meta = json.loads((Path(scene_dir) / TRUE_WATER_FILE).read_text())
    if meta.get("family") != "photo" or "generator" not in meta:
        raise ValueError(f"{scene_dir} is not a generated photo-family scene ({TRUE_WATER_FILE} family "
                         f"{meta.get('family')!r})")
    tuples = {f.name for f in dataclasses.fields(PhotoSynthConfig) if "tuple" in str(f.type)}
    data = {k: (_as_tuple(v) if k in tuples and v is not None else v) for k, v in meta["generator"].items()}
    return from_dict(PhotoSynthConfig, data)


def _as_tuple(v):
    return tuple(_as_tuple(x) for x in v) if isinstance(v, list) else v


@dataclass
class SurfaceTruth:
    """A photo-family scene's true seabed (module docstring)."""

    world: PhotoWorld
    ambient: float  # the generator's ambient share of the light
    linear_average: bool  # average colours in linear light (a "linear" water-space scene)

    def _points(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Point samples at flat x, y [M] → (height [M], colour [M, 3])."""
        t = self.world.terrain
        hs, cs = [], []
        for i in range(0, len(x), CHUNK):
            xs, ys = torch.as_tensor(x[i:i + CHUNK], dtype=F64), torch.as_tensor(y[i:i + CHUNK], dtype=F64)
            hs.append(bilinear(t.height_q, t.size, t.spacing, xs, ys).to(F64).numpy())
            cs.append(surface_colour(self.world, torch.stack([xs, ys], -1), self.ambient).numpy())
        return (np.concatenate(hs), np.concatenate(cs)) if hs else (np.zeros(0), np.zeros((0, 3)))

    def at(self, x, y, cell: float | None = None, samples: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """True height [*S] (metres, world z) and clean colour [*S, 3] (float [0, 1], clean/'s encoding) at world
        x, y (metres, equal shapes [*S]). ``cell``: metres; each value is then the mean over the cell × cell square
        centred there, from ``samples`` × ``samples`` point samples; None = point samples."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        if x.shape != y.shape:
            raise ValueError(f"x and y must have equal shapes, got {x.shape} and {y.shape}")
        if cell is None:
            h, c = self._points(x.reshape(-1), y.reshape(-1))
            return h.reshape(x.shape), c.reshape(*x.shape, 3)
        if cell <= 0 or samples < 1:
            raise ValueError(f"need cell > 0 and samples >= 1, got {cell} and {samples}")
        off = ((np.arange(samples) + 0.5) / samples - 0.5) * cell  # [k]
        ox, oy = (a.reshape(-1) for a in np.meshgrid(off, off, indexing="ij"))  # [k²]
        h, c = self._points((x.reshape(-1, 1) + ox).reshape(-1), (y.reshape(-1, 1) + oy).reshape(-1))
        h = h.reshape(-1, ox.size).mean(1)
        c = c.reshape(-1, ox.size, 3)
        c = linear_to_srgb(srgb_to_linear(c).mean(1)) if self.linear_average else c.mean(1)
        return h.reshape(x.shape), c.reshape(*x.shape, 3)


def load_surface_truth(scene_dir: str | Path) -> SurfaceTruth:
    """The true seabed of the photo-family scene in ``scene_dir`` (rebuilds its world; raises ValueError for
    another family, TextureFolderError when its texture photos are missing)."""
    cfg = scene_config(scene_dir)
    return SurfaceTruth(build_world(cfg), cfg.ambient, cfg.water_space == "linear")


def true_surface(scene_dir: str | Path, x, y, cell: float | None = None, samples: int = 4
                 ) -> tuple[np.ndarray, np.ndarray]:
    """True height [*S] (metres) and clean colour [*S, 3] at world x, y [*S] of a photo-family scene:
    ``load_surface_truth(scene_dir).at(x, y, cell, samples)``."""
    return load_surface_truth(scene_dir).at(x, y, cell, samples)


__all__ = ["SurfaceTruth", "load_surface_truth", "scene_config", "true_surface"]
