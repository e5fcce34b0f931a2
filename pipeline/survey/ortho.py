"""The true orthophoto: every map cell's seabed point (its x, y and the elevation model's height) looked up in the
photos that see it, tile by tile.

For each tile of the map grid and each photo whose footprint meets it, a cell's point is projected into the
training camera (is it in view, and is it the surface the model renders there, not something behind it: the
visibility test against the view's rendered depth) and through the photo's own lens (SfM's camera, distortion
included) to its pixel, sampled bilinearly. Each photo's sample is weighted by how well it sees the cell:
near (1/z²), head-on (cos² of the angle to the plane's normal), away from the photo's edges (a feather over 5 % of
its size), and by the restoration's confidence there; weights are raised to the 4th power before blending, so
the best photo dominates a cell while the hand-over between photos stays smooth (no seams, no ghosting of
several photos averaged). The same weights blend the restored photos (the de-watered mosaic) and the photos as
taken (the mosaic with water): the two mosaics differ only in the water.

Memory is bounded by one tile's arrays and a byte-limited cache of decoded photos; the mosaics go to memory-mapped
arrays that the GeoTIFF writer streams.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.scene.images import read_image
from pipeline.scene.records import LensCamera
from pipeline.survey.frame import SurveyFrame
from pipeline.survey.surface import MapGrid, ViewDepth, sample_dem

log = logging.getLogger(__name__)

TILE = 512  # cells per tile side
VISIBILITY_TOL = 0.03  # a cell is hidden when it lies this share of the range behind the rendered surface
FEATHER = 0.05  # the edge feather's width, as a share of the photo's shorter side
SHARPNESS = 4.0  # weights are raised to this power before blending


@dataclass(frozen=True)
class PhotoSource:
    """One registered photo as the mosaic reads it."""

    name: str
    depth: ViewDepth  # the training camera and its rendered surface depth
    lens: LensCamera  # the photo's own camera (SfM's, distortion included), at its own resolution
    photo: Path  # as taken
    restored: Path | None  # de-watered (None in mode 3dgs)
    confidence: Path | None  # the restoration's confidence map (8-bit)
    bounds: tuple[float, float, float, float]  # its surface's map footprint: x0, y0, x1, y1


class PhotoCache:
    """Decoded photos as uint8 [H, W, C], least recently used dropped beyond ``max_bytes``."""

    def __init__(self, max_bytes: int = 1_500_000_000) -> None:
        self.max_bytes, self.items, self.bytes = max_bytes, OrderedDict(), 0

    def get(self, path: Path, channels: int = 3) -> np.ndarray:
        if path in self.items:
            self.items.move_to_end(path)
            return self.items[path]
        arr = np.ascontiguousarray(np.round(read_image(path)[..., :channels] * 255).astype(np.uint8))
        self.items[path] = arr
        self.bytes += arr.nbytes
        while self.bytes > self.max_bytes and len(self.items) > 1:
            _, old = self.items.popitem(last=False)
            self.bytes -= old.nbytes
        return arr


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``img`` [H, W, C] sampled at array coordinates (x, y) [N] (pixel centres at integers), float32 [N, C]."""
    h, w = img.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    tx, ty = (x - x0).astype(np.float32)[:, None], (y - y0).astype(np.float32)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    a, b = img[y0, x0].astype(np.float32), img[y0, x1].astype(np.float32)
    c, d = img[y1, x0].astype(np.float32), img[y1, x1].astype(np.float32)
    return (a * (1 - tx) + b * tx) * (1 - ty) + (c * (1 - tx) + d * tx) * ty


@dataclass(frozen=True)
class Sighting:
    """Where one photo sees a tile's cells: the cells' indices, the photo's pixel positions (array coordinates),
    and the blending weight of each."""

    cells: np.ndarray  # [K] flat indices into the tile
    x: np.ndarray  # [K]
    y: np.ndarray  # [K]
    weight: np.ndarray  # [K] float64, before the confidence and the sharpening


def sight(src: PhotoSource, world: np.ndarray, normal: np.ndarray, z_ref: float) -> Sighting | None:
    """Which of the cells' seabed points ``world`` [N, 3] the photo sees, and where."""
    view = src.depth.view
    cam = world @ view.R.T + view.t
    z = cam[:, 2]
    c = view.camera
    with np.errstate(divide="ignore", invalid="ignore"):
        u = c.fx * cam[:, 0] / z + c.cx
        v = c.fy * cam[:, 1] / z + c.cy
    ok = (z > 1e-9) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
    idx = np.nonzero(ok)[0]
    if not idx.size:
        return None
    d = src.depth.depth[v[idx].astype(np.int64), u[idx].astype(np.int64)]
    vis = (d > 0) & (z[idx] <= d * (1 + VISIBILITY_TOL))  # nothing of the surface in front of the point
    idx = idx[vis]
    if not idx.size:
        return None
    px = np.asarray(src.lens.colmap().img_from_cam(cam[idx]), np.float64) - 0.5  # array coordinates
    W, H = src.lens.width, src.lens.height
    inside = (px[:, 0] >= 0) & (px[:, 0] <= W - 1) & (px[:, 1] >= 0) & (px[:, 1] <= H - 1)
    idx, px = idx[inside], px[inside]
    if not idx.size:
        return None
    ray = world[idx] - view.center
    rn = np.linalg.norm(ray, axis=1)
    cos = np.abs(ray @ normal) / np.maximum(rn, 1e-12)
    edge = np.minimum.reduce([px[:, 0], W - 1 - px[:, 0], px[:, 1], H - 1 - px[:, 1]])
    feather = np.clip(edge / (FEATHER * min(W, H)), 0.0, 1.0)
    weight = cos**2 * (z_ref / z[idx]) ** 2 * feather
    return Sighting(idx, px[:, 0], px[:, 1], weight)


@dataclass
class MosaicTile:
    """One tile's products: the de-watered mosaic (None without restored photos), the mosaic with water, the
    confidence (uint8) and the heights (float32, NaN unseen)."""

    restored: np.ndarray | None  # [h, w, 3] uint8
    water: np.ndarray  # [h, w, 3] uint8
    valid: np.ndarray  # [h, w] bool: some photo saw the cell
    confidence: np.ndarray  # [h, w] uint8
    height: np.ndarray  # [h, w] float32


def mosaic_tile(grid: MapGrid, window: tuple[int, int, int, int], dem: np.ndarray, dem_grid: MapGrid,
                frame: SurveyFrame, sources: list[PhotoSource], cache: PhotoCache, z_ref: float) -> MosaicTile:
    """The products of the grid cells rows r0:r1, columns c0:c1."""
    r0, r1, c0, c1 = window
    x, y = grid.centres(r0, r1, c0, c1)
    h = sample_dem(dem, dem_grid, x, y)
    shape = x.shape
    n = x.size
    seen = np.isfinite(h.ravel())
    world = frame.to_world(np.stack([x.ravel(), y.ravel(), np.where(seen, h.ravel(), 0.0)], 1)[seen])
    cells = np.nonzero(seen)[0]
    has_restored = any(s.restored is not None for s in sources)
    acc_r, acc_w = np.zeros((n, 3)), np.zeros((n, 3))
    wsum, csum = np.zeros(n), np.zeros(n)
    tx0, tx1 = grid.x0 + c0 * grid.gsd, grid.x0 + c1 * grid.gsd
    ty1, ty0 = grid.y1 - r0 * grid.gsd, grid.y1 - r1 * grid.gsd
    normal_world = frame.Q[2]
    for src in sources:
        bx0, by0, bx1, by1 = src.bounds
        if bx1 < tx0 or bx0 > tx1 or by1 < ty0 or by0 > ty1 or not cells.size:
            continue
        s = sight(src, world, normal_world, z_ref)
        if s is None:
            continue
        conf = np.ones(len(s.cells))
        if src.confidence is not None:
            cmap = cache.get(src.confidence, channels=1)
            conf = bilinear(cmap, s.x, s.y)[:, 0].astype(np.float64) / 255.0
        w = (s.weight * np.maximum(conf, 0.02)) ** SHARPNESS
        at = cells[s.cells]
        acc_w[at] += w[:, None] * bilinear(cache.get(src.photo), s.x, s.y)[:, :3]
        if src.restored is not None:
            acc_r[at] += w[:, None] * bilinear(cache.get(src.restored), s.x, s.y)[:, :3]
        wsum[at] += w
        csum[at] += w * conf
    valid = wsum > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(valid, 1.0 / wsum, 0.0)[:, None]

    def image(acc: np.ndarray) -> np.ndarray:
        return np.clip(np.round(acc * inv), 0, 255).astype(np.uint8).reshape(*shape, 3)

    conf_img = np.clip(np.round(255 * csum * inv[:, 0]), 0, 255).astype(np.uint8).reshape(shape)
    return MosaicTile(image(acc_r) if has_restored else None, image(acc_w), valid.reshape(shape), conf_img,
                      h.astype(np.float32))


def tiles(grid: MapGrid, size: int = TILE):
    for r0 in range(0, grid.height, size):
        for c0 in range(0, grid.width, size):
            yield r0, min(r0 + size, grid.height), c0, min(c0 + size, grid.width)


def make_mosaics(grid: MapGrid, dem: np.ndarray, dem_grid: MapGrid, frame: SurveyFrame, sources: list[PhotoSource],
                 out: dict[str, np.ndarray], z_ref: float, cache: PhotoCache | None = None,
                 on_tile: Callable[[int, int], None] = lambda k, n: None) -> None:
    """Fill ``out``'s arrays (grid-sized, e.g. memory-mapped): "water" [H, W, 3] uint8, "valid" [H, W] bool,
    "confidence" [H, W] uint8, "height" [H, W] float32 and, with restored photos, "restored" [H, W, 3] uint8."""
    cache = cache or PhotoCache()
    windows = list(tiles(grid))
    for k, win in enumerate(windows):
        r0, r1, c0, c1 = win
        t = mosaic_tile(grid, win, dem, dem_grid, frame, sources, cache, z_ref)
        out["water"][r0:r1, c0:c1] = t.water
        out["valid"][r0:r1, c0:c1] = t.valid
        out["confidence"][r0:r1, c0:c1] = t.confidence
        out["height"][r0:r1, c0:c1] = t.height
        if t.restored is not None and "restored" in out:
            out["restored"][r0:r1, c0:c1] = t.restored
        on_tile(k + 1, len(windows))


__all__ = ["PhotoCache", "PhotoSource", "bilinear", "make_mosaics", "mosaic_tile", "sight", "tiles"]
