"""The reconstructed surface as the products need it: each view's rendered depth (for the altimeter's scale, the
scale bars and the orthomosaic's visibility test) and the elevation model, the heights of every view's surface
pixels gathered on the map grid.

Depth is the model's expected camera z (scene units) at the training resolution, kept where the render is opaque
(alpha ≥ 0.5: the seabed, not the water). A DEM cell's height is the weighted mean of the surface points that fall
in it, weighted towards near, head-on views (1/z², the cosine of the view angle); small holes are filled from their
neighbours, larger ones stay nodata.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.scene.records import View
from pipeline.survey.frame import SurveyFrame
from pipeline.train.model import TrainedModel
from pipeline.train.render import render_outputs

log = logging.getLogger(__name__)

SURFACE_ALPHA = 0.5
CENTRE_WINDOW = 0.1  # the altimeter's footprint: this share of the image's width and height around its centre


@dataclass(frozen=True)
class ViewDepth:
    view: View  # the training camera
    depth: np.ndarray  # [h, w] float32 camera z, scene units; 0 where the render is not surface

    def point_at(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] under training-camera pixel positions (u, v: pixel-centre convention) and whether
        the render holds surface there (nearest pixel)."""
        h, w = self.depth.shape
        iu = np.clip(np.floor(u).astype(int), 0, w - 1)
        iv = np.clip(np.floor(v).astype(int), 0, h - 1)
        z = self.depth[iv, iu].astype(np.float64)
        c = self.view.camera
        cam = np.stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z], -1)
        return (cam - self.view.t) @ self.view.R, z > 0


def render_depths(model: TrainedModel, views: list[View]) -> list[ViewDepth]:
    """Every view's surface depth at its training resolution."""
    out = []
    for view in views:
        o = render_outputs(model.gaussians, view, None, model.sh_degree, background=model.background)
        out.append(ViewDepth(view, np.where(o.alpha >= SURFACE_ALPHA, o.depth, 0).astype(np.float32)))
    return out


def centre_distance(vd: ViewDepth) -> float | None:
    """The model's camera-to-bottom distance of one view (scene units): the median surface depth in a window
    around the principal point, where a downward altimeter beside the camera reads; None when that window shows
    no surface."""
    c = vd.view.camera
    hw, hh = max(1, int(CENTRE_WINDOW * c.width / 2)), max(1, int(CENTRE_WINDOW * c.height / 2))
    cx, cy = int(c.cx), int(c.cy)
    win = vd.depth[max(0, cy - hh):cy + hh + 1, max(0, cx - hw):cx + hw + 1]
    win = win[win > 0]
    return float(np.median(win)) if win.size >= 0.5 * (2 * hw + 1) * (2 * hh + 1) else None


def surface_points(vd: ViewDepth, frame: SurveyFrame, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The view's surface pixels as map points [N, 3] and their weights [N] (1/z² · cos of the view angle)."""
    h, w = vd.depth.shape
    v, u = np.mgrid[0:h:step, 0:w:step]
    u, v = u.ravel() + 0.5, v.ravel() + 0.5
    world, ok = vd.point_at(u, v)
    world, z = world[ok], vd.depth[::step, ::step].ravel()[ok].astype(np.float64)
    ray = world - vd.view.center
    cos = np.abs(ray @ frame.Q[2]) / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
    return frame.to_map(world), cos / np.maximum(z, 1e-9) ** 2


@dataclass(frozen=True)
class MapGrid:
    """A north-up grid on the map: cell (row, col) centre at (x0 + (col + ½)·gsd, y1 − (row + ½)·gsd)."""

    x0: float  # left edge
    y1: float  # top edge
    gsd: float
    width: int
    height: int

    def centres(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        cols = self.x0 + (np.arange(c0, c1) + 0.5) * self.gsd
        rows = self.y1 - (np.arange(r0, r1) + 0.5) * self.gsd
        return np.meshgrid(cols, rows)

    def cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) integer cells of map points (may fall outside the grid)."""
        return np.floor((self.y1 - y) / self.gsd).astype(np.int64), np.floor((x - self.x0) / self.gsd).astype(np.int64)

    def coarser(self, factor: int) -> MapGrid:
        return MapGrid(self.x0, self.y1, self.gsd * factor, -(-self.width // factor), -(-self.height // factor))


def grid_around(points: np.ndarray, gsd: float, trim: float = 0.5, max_cells: float = 4e8) -> MapGrid:
    """The grid covering the map points' x, y (the outermost ``trim`` % on each side left out: stray Gaussians far
    off the survey do not stretch it), snapped to whole cells."""
    lo = np.percentile(points[:, :2], trim, axis=0)
    hi = np.percentile(points[:, :2], 100 - trim, axis=0)
    x0, y0 = np.floor(lo / gsd) * gsd
    x1, y1 = np.ceil(hi / gsd) * gsd
    w, h = int(round((x1 - x0) / gsd)), int(round((y1 - y0) / gsd))
    if w * h > max_cells:
        raise ValueError(f"a {w}x{h} grid at {gsd:g} per cell is too large; choose a coarser ortho_gsd")
    return MapGrid(float(x0), float(y1), float(gsd), max(w, 1), max(h, 1))


def accumulate_heights(grid: MapGrid, batches) -> tuple[np.ndarray, np.ndarray]:
    """Σ w·h and Σ w per cell [H, W] (float64) over batches of (map points [N, 3], weights [N])."""
    sw = np.zeros(grid.height * grid.width)
    swh = np.zeros(grid.height * grid.width)
    for pts, wts in batches:
        r, c = grid.cell(pts[:, 0], pts[:, 1])
        ok = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
        idx = r[ok] * grid.width + c[ok]
        sw += np.bincount(idx, wts[ok], minlength=sw.size)
        swh += np.bincount(idx, wts[ok] * pts[ok, 2], minlength=sw.size)
    return swh.reshape(grid.height, grid.width), sw.reshape(grid.height, grid.width)


def fill_small_holes(dem: np.ndarray, rounds: int = 2) -> np.ndarray:
    """NaN cells with at least 3 valid 8-neighbours take their mean; ``rounds`` times (holes up to about 2·rounds
    cells across close; larger gaps stay nodata: nothing saw them)."""
    out = dem.copy()
    for _ in range(rounds):
        valid = np.isfinite(out)
        pad_v = np.pad(valid, 1)
        pad = np.pad(np.where(valid, out, 0), 1)
        n = sum(pad_v[1 + dy:pad_v.shape[0] - 1 + dy, 1 + dx:pad_v.shape[1] - 1 + dx]
                for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
        s = sum(pad[1 + dy:pad.shape[0] - 1 + dy, 1 + dx:pad.shape[1] - 1 + dx]
                for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
        fill = ~valid & (n >= 3)
        if not fill.any():
            break
        out[fill] = s[fill] / n[fill]
    return out


def coarse_dem(grid: MapGrid, depths: list[ViewDepth], frame: SurveyFrame) -> np.ndarray:
    """Heights [H, W] float64 on ``grid`` (NaN: unseen) from every view's surface points."""
    swh, sw = accumulate_heights(grid, (surface_points(vd, frame) for vd in depths))
    with np.errstate(invalid="ignore", divide="ignore"):
        dem = np.where(sw > 0, swh / sw, np.nan)
    return fill_small_holes(dem)


def sample_dem(dem: np.ndarray, grid: MapGrid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear heights at map points from a DEM on ``grid`` (NaN where any of the four nodes is NaN or outside;
    at the grid's outer half-cell the nearest row/column is used)."""
    fc = (x - grid.x0) / grid.gsd - 0.5
    fr = (grid.y1 - y) / grid.gsd - 0.5
    fc = np.clip(fc, 0, grid.width - 1)
    fr = np.clip(fr, 0, grid.height - 1)
    c0 = np.minimum(np.floor(fc).astype(np.int64), max(grid.width - 2, 0))
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(grid.height - 2, 0))
    c1, r1 = np.minimum(c0 + 1, grid.width - 1), np.minimum(r0 + 1, grid.height - 1)
    tc, tr = fc - c0, fr - r0
    return ((dem[r0, c0] * (1 - tc) + dem[r0, c1] * tc) * (1 - tr) + (dem[r1, c0] * (1 - tc) + dem[r1, c1] * tc) * tr)


__all__ = ["MapGrid", "ViewDepth", "centre_distance", "coarse_dem", "grid_around", "render_depths", "sample_dem",
           "surface_points"]
