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
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.scene.records import View
from pipeline.splat.gaussians import activate
from pipeline.splat.rasterize import rasterize
from pipeline.survey.frame import SurveyFrame
from pipeline.train.model import TrainedModel
from pipeline.train.render import view_tensors

log = logging.getLogger(__name__)

SURFACE_ALPHA = 0.5
CENTRE_WINDOW = 0.1  # the altimeter's footprint: this share of the image's width and height around its centre
MIN_SPREAD = 0.005  # relative depth spread: a floor under a pixel's height uncertainty (surface_points)
MAX_SPREAD = 0.05  # a pixel whose blend spreads more than this is two surfaces, not one: left out of the DEM
WELL_SEEN_COS = 0.8  # a trusted cell's best view is at least this share of the survey's typical best cosine
WELL_SEEN_RANGE = 1.5  # and at most this many times the survey's typical nearest range (well_seen)
SMOOTH_RADIUS = 1  # cells: the DEM's denoising mean is (2k + 1)² cells (smooth)
DESPECKLE_WINDOW = 5  # cells: the neighbourhood a DEM cell is compared with (despeckle)
DESPECKLE_SIGMAS = 4.0  # robust standard deviations a cell may stand out of it


@dataclass(frozen=True)
class ViewDepth:
    view: View  # the training camera
    depth: np.ndarray  # [h, w] float32 camera z, scene units; 0 where the render is not surface
    spread: np.ndarray | None = None  # [h, w] float32: the blended Gaussians' depth spread / depth (depth_spread)

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


def depth_spread(gaussians: dict[str, torch.Tensor], view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(expected depth E[z], relative spread sqrt(E[z²] − E[z]²) / E[z], alpha) [h, w] of one view: the
    rasterizer blends each Gaussian's camera z and z² as its colour. Where the blend mixes surfaces at different
    depths (a floater in front, an edge, a thick fuzzy layer) the spread is large and the expected depth lies between
    them: on a generated survey, pixels with a spread under 1.5 % had half the depth error of all pixels."""
    g = activate(gaussians)
    viewmat, K = view_tensors(view, torch.device("cpu"))
    with torch.no_grad():
        z = g.means @ viewmat[2, :3] + viewmat[2, 3]
        feats = torch.stack([z, z * z, torch.zeros_like(z)], 1)
        out, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, feats, viewmat[None], K[None],
                                  view.camera.width, view.camera.height, render_mode="RGB")
    a = alpha[0, ..., 0].numpy().astype(np.float64)
    o = out[0].numpy().astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ez = np.where(a > 1e-6, o[..., 0] / a, 0.0)
        ez2 = np.where(a > 1e-6, o[..., 1] / a, 0.0)
        spread = np.where(ez > 0, np.sqrt(np.maximum(ez2 - ez**2, 0.0)) / ez, np.inf)
    return ez, spread, a


def render_depths(model: TrainedModel, views: list[View]) -> list[ViewDepth]:
    """Every view's surface depth at its training resolution, with its spread (:func:`depth_spread`)."""
    out = []
    for view in views:
        ez, spread, alpha = depth_spread(model.gaussians, view)
        surface = alpha >= SURFACE_ALPHA
        out.append(ViewDepth(view, np.where(surface, ez, 0).astype(np.float32),
                             np.where(surface, spread, np.inf).astype(np.float32)))
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


def surface_points(vd: ViewDepth, frame: SurveyFrame, step: int = 1
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The view's surface pixels as map points [N, 3], their weights [N], the cosine of the view angle and the
    range (scene units). A pixel's weight is the inverse variance of its height: range × its depth spread (at least
    MIN_SPREAD), over the cosine; pixels spread beyond MAX_SPREAD are left out."""
    h, w = vd.depth.shape
    v, u = np.mgrid[0:h:step, 0:w:step]
    u, v = u.ravel() + 0.5, v.ravel() + 0.5
    world, ok = vd.point_at(u, v)
    spread = np.full(ok.shape, MIN_SPREAD) if vd.spread is None else vd.spread[::step, ::step].ravel()
    ok &= spread <= MAX_SPREAD
    world, spread = world[ok], np.maximum(spread[ok], MIN_SPREAD)
    ray = world - vd.view.center
    dist = np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
    cos = np.abs(ray @ frame.Q[2]) / dist
    return frame.to_map(world), cos**2 / (dist * spread) ** 2, cos, dist


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


@dataclass
class HeightSums:
    """Per cell of a grid (flat [H·W]): Σ w·h, Σ w, the best (largest) cosine and the nearest range any view saw
    it at, and how many views saw it."""

    swh: np.ndarray
    sw: np.ndarray
    best_cos: np.ndarray
    nearest: np.ndarray
    views: np.ndarray


def accumulate_heights(grid: MapGrid, batches) -> HeightSums:
    """:class:`HeightSums` over batches (one per view) of :func:`surface_points` output."""
    n = grid.height * grid.width
    acc = HeightSums(np.zeros(n), np.zeros(n), np.zeros(n), np.full(n, np.inf), np.zeros(n, np.int32))
    for pts, wts, cos, dist in batches:
        r, c = grid.cell(pts[:, 0], pts[:, 1])
        ok = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
        idx = r[ok] * grid.width + c[ok]
        acc.sw += np.bincount(idx, wts[ok], minlength=n)
        acc.swh += np.bincount(idx, wts[ok] * pts[ok, 2], minlength=n)
        np.maximum.at(acc.best_cos, idx, cos[ok])
        np.minimum.at(acc.nearest, idx, dist[ok])
        acc.views[np.unique(idx)] += 1
    return acc


def well_seen(acc: HeightSums) -> np.ndarray:
    """Cells whose height can be trusted: seen by two views or more, by one of them nearly as head-on
    (WELL_SEEN_COS of the survey's typical best cosine) and nearly as near (WELL_SEEN_RANGE times the typical
    nearest range) as the survey sees its seabed. What only an oblique view saw from afar is where the rendered
    depth is worst (the water hides the seabed there): on a generated medium scene those cells had 3x the
    height error of the rest (docs/DECISIONS.md, "Survey products")."""
    seen = acc.sw > 0
    if not seen.any():
        return seen
    cos0, near0 = np.median(acc.best_cos[seen]), np.median(acc.nearest[seen])
    ok = seen & (acc.best_cos >= WELL_SEEN_COS * cos0) & (acc.nearest <= WELL_SEEN_RANGE * near0)
    two = ok & (acc.views >= 2)
    return two if two.sum() >= 0.25 * ok.sum() else ok  # a survey with little overlap keeps its single views


def neighbour_sums(dem: np.ndarray, k: int = 1, centre: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(sum, count) [H, W] of each cell's valid (finite) neighbours within ``k`` cells; the cell itself counts when
    ``centre``."""
    valid = np.isfinite(dem)
    pad, count = np.pad(np.where(valid, dem, 0.0), k), np.pad(valid.astype(np.float64), k)
    shifts = [(dy, dx) for dy in range(-k, k + 1) for dx in range(-k, k + 1) if centre or dy or dx]
    total = sum(pad[k + dy:pad.shape[0] - k + dy, k + dx:pad.shape[1] - k + dx] for dy, dx in shifts)
    n = sum(count[k + dy:count.shape[0] - k + dy, k + dx:count.shape[1] - k + dx] for dy, dx in shifts)
    return total, n


def fill_small_holes(dem: np.ndarray, rounds: int = 2) -> np.ndarray:
    """NaN cells with at least 3 valid 8-neighbours take their mean; ``rounds`` times (holes up to about 2·rounds
    cells across close; larger gaps stay nodata: nothing saw them)."""
    out = dem.copy()
    for _ in range(rounds):
        total, n = neighbour_sums(out)
        fill = ~np.isfinite(out) & (n >= 3)
        if not fill.any():
            break
        out[fill] = total[fill] / n[fill]
    return out


def despeckle(dem: np.ndarray, k: int = DESPECKLE_WINDOW, limit: float = DESPECKLE_SIGMAS) -> np.ndarray:
    """``dem`` without the cells that stand out of their k x k neighbourhood's median by more than ``limit``
    robust standard deviations of all cells' departures: a floater (Gaussians in the water drawn opaque in a
    view) makes a spike, the seabed does not; cells with under a quarter of their neighbours valid go too. On a
    generated survey (16 views, test size) this took the height error's RMS from 0.52 m to 0.11 m (median 4 cm
    before and after: docs/DECISIONS.md, "Survey products")."""
    pad = np.pad(dem, k // 2, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(pad, (k, k))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: no neighbourhood, the cell stays
        med = np.nanmedian(windows.reshape(*dem.shape, k * k), axis=-1)
    dev = dem - med
    ok = np.isfinite(dev)
    if ok.sum() < 10:
        return dem
    sigma = 1.4826 * np.median(np.abs(dev[ok] - np.median(dev[ok])))
    lonely = np.isfinite(windows).sum(axis=(-2, -1)) < k * k // 4  # a few cells alone: floaters, not seabed
    return np.where((np.abs(dev) > limit * max(sigma, 1e-12)) | lonely, np.nan, dem)


def coarse_dem(grid: MapGrid, depths: list[ViewDepth], frame: SurveyFrame) -> np.ndarray:
    """Heights [H, W] float64 on ``grid`` (NaN: unseen, not :func:`well_seen`, or a :func:`despeckle` spike) from
    every view's surface points."""
    acc = accumulate_heights(grid, (surface_points(vd, frame) for vd in depths))
    keep = well_seen(acc)
    with np.errstate(invalid="ignore", divide="ignore"):
        dem = np.where(keep, acc.swh / acc.sw, np.nan).reshape(grid.height, grid.width)
    return smooth(fill_small_holes(despeckle(dem)))


def smooth(dem: np.ndarray, k: int = SMOOTH_RADIUS) -> np.ndarray:
    """The mean of each valid cell's valid neighbours within ``k`` cells (NaN stays NaN). The rendered depth's
    pixel noise inflates the DEM's rugosity: on a generated survey 1.84 against the true 1.35; a 3 x 3 mean gives
    1.53 and changes the height error by < 2 mm (docs/DECISIONS.md, "Survey products")."""
    total, n = neighbour_sums(dem, k, centre=True)
    return np.where(np.isfinite(dem), total / np.maximum(n, 1.0), np.nan)


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
