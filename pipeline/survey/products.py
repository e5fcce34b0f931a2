"""The survey's raster products on one grid: the de-watered orthomosaic, the mosaic with water, its confidence and
the elevation model, written as Cloud-Optimized GeoTIFFs with previews, and the reef-structure numbers.

The grid's ground resolution defaults to the photos' own at the median range (range × metres per unit / the
photo's focal length in pixels). The elevation model is gathered on a coarser grid matching the rendered depth's
own resolution (training pixels on the seabed) and sampled bilinearly onto the product grid.
"""

from __future__ import annotations

import logging
import math
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.evaluate.evaluation import json_safe
from pipeline.job.layout import JobLayout
from pipeline.survey.geotiff import Grid, write_cog, write_preview
from pipeline.survey.measure import SurveyGeometry
from pipeline.survey.ortho import PhotoCache, PhotoSource, make_mosaics
from pipeline.survey.surface import MapGrid, coarse_dem, surface_points
from pipeline.survey.terrain import height_range, hillshade, rugosity, tile_stats

log = logging.getLogger(__name__)

MAX_CELLS = 6e8  # beyond this the ground resolution is coarsened (with a warning), never a failed job
TILE_STATS_M = 5.0  # side of the per-tile table's tiles, metres (scene units without a scale)


class NoSurfaceError(ValueError):
    """Nothing of the seabed to map (no registered photo shows surface at its centre or anywhere)."""


def lens_focal(lens) -> float:
    """The photo's focal length in pixels (COLMAP's models put f or fx first)."""
    return float(lens.params[0])


def default_gsd(geom: SurveyGeometry, lenses: dict) -> float:
    """The photos' own ground resolution at the median range, in map units per pixel."""
    per = [geom.distances[n] / lens_focal(lenses[n]) for n in geom.distances if n in lenses]
    if not per:
        raise NoSurfaceError("no view shows the seabed at its centre: the ground resolution is unknown "
                             "(give ortho_gsd)")
    return float(np.median(per)) * geom.frame.scale


def view_bounds(vd, frame) -> tuple[float, float, float, float] | None:
    pts = surface_points(vd, frame, step=4)[0]
    if len(pts) < 16:
        return None
    lo, hi = np.percentile(pts[:, :2], 0.5, axis=0), np.percentile(pts[:, :2], 99.5, axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def product_grid(bounds: list[tuple[float, float, float, float]], gsd: float, warnings: list[str]) -> MapGrid:
    x0 = min(b[0] for b in bounds)
    y0 = min(b[1] for b in bounds)
    x1 = max(b[2] for b in bounds)
    y1 = max(b[3] for b in bounds)
    cells = (x1 - x0) * (y1 - y0) / gsd**2
    if cells > MAX_CELLS:
        new = gsd * math.sqrt(cells / MAX_CELLS)
        warnings.append(f"ground resolution {gsd:.4g} gives {cells:.3g} cells; coarsened to {new:.4g}")
        gsd = new
    x0, y0 = math.floor(x0 / gsd) * gsd, math.floor(y0 / gsd) * gsd
    x1, y1 = math.ceil(x1 / gsd) * gsd, math.ceil(y1 / gsd) * gsd
    return MapGrid(x0, y1, gsd, max(1, round((x1 - x0) / gsd)), max(1, round((y1 - y0) / gsd)))


def crop_to(grid: MapGrid, dem: np.ndarray, factor: int) -> tuple[MapGrid, np.ndarray]:
    """The product grid and the coarse DEM cut to the DEM's trusted cells (the footprints' far, oblique fringes
    that the DEM left out would be empty mosaic)."""
    rows, cols = np.nonzero(np.isfinite(dem).any(1))[0], np.nonzero(np.isfinite(dem).any(0))[0]
    if not rows.size:
        raise NoSurfaceError("no seabed was seen well enough to map (two views, near and head-on)")
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    g = MapGrid(grid.x0 + int(c0) * factor * grid.gsd, grid.y1 - int(r0) * factor * grid.gsd, grid.gsd,
                int(min(grid.width - c0 * factor, (c1 - c0) * factor)),
                int(min(grid.height - r0 * factor, (r1 - r0) * factor)))
    return g, dem[r0:r1, c0:c1]


@dataclass(frozen=True)
class Products:
    grid: MapGrid
    record: dict


def make_products(job: Path, geom: SurveyGeometry, lenses: dict, restored: dict[str, str], gsd: float | None,
                  on_progress=lambda f, m: None) -> Products:
    """Write the products into ``JobLayout(job).survey``; returns the grid and what survey.json records of them."""
    layout = JobLayout(job)
    frame = geom.frame
    warnings = geom.warnings
    gsd = gsd or default_gsd(geom, lenses)
    sources, bounds = [], []
    for name, vd in geom.depths.items():
        b = view_bounds(vd, frame)
        if b is None or name not in lenses:
            continue
        bounds.append(b)
        stem = Path(name).stem
        conf = layout.confidence / f"{stem}.png"
        sources.append(PhotoSource(name, vd, lenses[name], layout.images / name,
                                   layout.restored / restored[name] if name in restored else None,
                                   conf if name in restored and conf.is_file() else None, b))
    if not sources:
        raise NoSurfaceError("no registered photo shows the seabed: nothing to map")
    grid = product_grid(bounds, gsd, warnings)
    # the DEM where the rendered depth has its own resolution: training pixels on the seabed
    train_gsd = float(np.median([geom.distances[s.name] / s.depth.view.camera.fx for s in sources
                                 if s.name in geom.distances])) * frame.scale
    factor = max(1, int(round(train_gsd / grid.gsd)))
    dem_grid = grid.coarser(factor)
    dem = coarse_dem(dem_grid, [s.depth for s in sources], frame)
    grid, dem = crop_to(grid, dem, factor)
    dem_grid = grid.coarser(factor)
    on_progress(0.2, "elevation model gathered")
    shutil.rmtree(layout.survey, ignore_errors=True)
    work = layout.survey / ".work"
    work.mkdir(parents=True)
    H, W = grid.height, grid.width
    out = {"water": np.lib.format.open_memmap(work / "water.npy", "w+", np.uint8, (H, W, 3)),
           "valid": np.lib.format.open_memmap(work / "valid.npy", "w+", np.bool_, (H, W)),
           "confidence": np.lib.format.open_memmap(work / "confidence.npy", "w+", np.uint8, (H, W)),
           "height": np.lib.format.open_memmap(work / "height.npy", "w+", np.float32, (H, W))}
    has_restored = any(s.restored is not None for s in sources)
    if has_restored:
        out["restored"] = np.lib.format.open_memmap(work / "restored.npy", "w+", np.uint8, (H, W, 3))
    z_ref = float(np.median(list(geom.distances.values())))
    make_mosaics(grid, dem, dem_grid, frame, sources, out, z_ref, PhotoCache(),
                 lambda k, n: on_progress(0.2 + 0.6 * k / n, f"mosaic tile {k}/{n}"))
    g = Grid(grid.x0, grid.y1, grid.gsd, W, H, frame.epsg, frame.crs_name)
    files = {}
    mask = out["valid"]
    if has_restored:
        write_cog(layout.ortho, out["restored"], g, mask=mask)
        write_preview(layout.ortho_preview, out["restored"], mask=mask)
        files["ortho"] = layout.relative(layout.ortho)
        files["ortho_preview"] = layout.relative(layout.ortho_preview)
    write_cog(layout.ortho_water, out["water"], g, mask=mask)
    write_preview(layout.ortho_water_preview, out["water"], mask=mask)
    write_cog(layout.ortho_confidence, out["confidence"], g, mask=mask)
    height = out["height"]
    write_cog(layout.dem, height, g, nodata=float("nan"))
    shade = hillshade(height, grid.gsd)
    write_preview(layout.hillshade_preview, shade, mask=np.isfinite(height))
    files.update({"ortho_water": layout.relative(layout.ortho_water),
                  "ortho_water_preview": layout.relative(layout.ortho_water_preview),
                  "ortho_confidence": layout.relative(layout.ortho_confidence),
                  "dem": layout.relative(layout.dem), "hillshade_preview": layout.relative(layout.hillshade_preview)})
    on_progress(0.9, "products written")
    terrain = json_safe({"rugosity": rugosity(height, grid.gsd), "height": asdict(height_range(height)),
                      "tile_m": TILE_STATS_M,
                      "tiles": [asdict(t) for t in tile_stats(height, grid.gsd, TILE_STATS_M, (grid.x0, grid.y1))]})
    valid_share = float(mask.mean())
    rec = {"grid": {"gsd": grid.gsd, "width": W, "height": H, "units": geom.units,
                    "bounds": [grid.x0, grid.y1 - H * grid.gsd, grid.x0 + W * grid.gsd, grid.y1],
                    "area": float(mask.sum()) * grid.gsd**2, "covered_share": round(valid_share, 4),
                    "dem_gsd": dem_grid.gsd, "photos": len(sources)},
           "terrain": terrain, "files": files}
    shutil.rmtree(work, ignore_errors=True)
    return Products(grid, rec)


__all__ = ["NoSurfaceError", "Products", "default_gsd", "make_products"]
