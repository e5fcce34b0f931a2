"""Reef-structure numbers from an elevation model: rugosity, height range, per-tile statistics, hillshade.

The DEM is ``[H, W]`` float heights in metres (float32 on disk) on a north-up grid of square cells of ``gsd``
metres: row 0 is the northern edge, columns run east, heights are samples at the cell centres, NaN where the
survey saw nothing. Pure functions: arrays in, numbers out. A DEM of any size (a numpy memmap is fine) is read
in row blocks of about a million cells, so the temporaries stay bounded whatever its size (measured on a 3000 x
3000 memmap: 43 MB for rugosity, 50 for height_range, 144 for hillshade besides its uint8 output); areas and
moments are summed in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_BLOCK_CELLS = 1 << 20  # DEM cells per row block: float64 temporaries of 8 MB each
_HISTOGRAM_BINS = 1 << 20  # large DEMs' percentiles to within (max - min) / 2^20: 5 µm over 5 m; 8 MB of counts


@dataclass(frozen=True)
class HeightRange:
    """Statistics of the valid heights of a DEM, metres (NaN when ``valid`` is 0)."""

    valid: int
    """Cells with a height."""
    min: float
    max: float
    p2: float
    """2nd percentile (numpy's default linear interpolation); exact up to a million valid cells, beyond that
    from a histogram, to within (max - min) / 2^20."""
    p98: float
    """98th percentile, likewise."""
    robust_range: float
    """p98 - p2: the relief without the outliers (a stray fish, a spike at the survey's edge)."""
    mean: float
    std: float
    """Population standard deviation (ddof = 0, as numpy's std)."""


@dataclass(frozen=True)
class TileStats:
    """The structure numbers of one square tile of a DEM."""

    row: int
    """Tile row, 0 at the north edge."""
    col: int
    """Tile column, 0 at the west edge."""
    bounds: tuple[float, float, float, float]
    """(left, bottom, right, top) in metres, in the frame of ``tile_stats``'s ``origin``; clipped to the DEM."""
    valid_share: float
    """Share of the tile's cells with a height."""
    rugosity: float
    """Surface / planar area of the tile's valid quads (NaN if none)."""
    surface_m2: float
    """3D surface area of those quads, m²."""
    planar_m2: float
    """Their planar area, m²."""
    heights: HeightRange


def rugosity(dem: np.ndarray, gsd: float) -> float:
    """Surface rugosity: 3D surface area / planar area, over the 2x2 quads whose four corners have a height.

    Each quad (heights z00 z01 / z10 z11, columns east, rows south, corners ``gsd`` apart) is split along its
    z00-z11 diagonal into two triangles. A triangle whose legs rise by p·g and q·g over the two axes has area
    ½g²·√(1 + p² + q²) over a planar ½g², so the rugosity is the mean of √(1 + p² + q²) over the triangles,
    with (p, q) = ((z01 - z00)/g, (z11 - z01)/g) and ((z11 - z10)/g, (z10 - z00)/g). A plane is exact: flat
    gives 1, z = a·x gives √(1 + a²). NaN when no quad is valid.

    >>> rugosity(np.zeros((3, 3), np.float32), 0.1)
    1.0
    """
    root_sum, triangles = _surface_sums(dem, gsd)
    return root_sum / triangles if triangles else math.nan


def height_range(dem: np.ndarray) -> HeightRange:
    """Min, max, 2nd and 98th percentiles and their difference, mean and standard deviation of the valid
    (non-NaN) heights of ``dem`` ([H, W]); two passes in row blocks. The percentiles are numpy's when the valid
    heights fit in one block (a million), else read from a 2^20-bin histogram, to within (max - min) / 2^20."""
    _check_dem(dem)
    count, total, low, high = 0, 0.0, math.inf, -math.inf
    for block in _row_blocks(dem):
        z = block[~np.isnan(block)]
        if z.size:
            count += z.size
            total += float(z.sum())
            low, high = min(low, float(z.min())), max(high, float(z.max()))
    if count == 0:
        return HeightRange(0, *([math.nan] * 7))
    mean = total / count
    squares = 0.0
    exact = count <= _BLOCK_CELLS  # the valid heights fit in one block: numpy's exact percentiles
    values: list[np.ndarray] = []
    counts = np.zeros(0 if exact else _HISTOGRAM_BINS, dtype=np.int64)
    scale = _HISTOGRAM_BINS / (high - low) if high > low else 0.0
    for block in _row_blocks(dem):
        z = block[~np.isnan(block)]
        squares += float(np.square(z - mean).sum())
        if exact:
            values.append(z)
        else:
            bins = np.minimum(((z - low) * scale).astype(np.int64), _HISTOGRAM_BINS - 1)
            counts += np.bincount(bins, minlength=_HISTOGRAM_BINS)
    if exact:
        p2, p98 = (float(v) for v in np.percentile(np.concatenate(values), [2.0, 98.0]))
    else:
        p2, p98 = (_percentile(counts, count, low, high, q) for q in (2.0, 98.0))
    return HeightRange(count, low, high, p2, p98, p98 - p2, mean, math.sqrt(squares / count))


def tile_stats(
    dem: np.ndarray, gsd: float, tile_m: float, origin: tuple[float, float] = (0.0, 0.0)
) -> list[TileStats]:
    """The structure numbers of each square tile of side ``tile_m`` metres, row by row from the north-west.

    The side is rounded to whole cells (at least one); tiles at the south and east edges are clipped to the DEM.
    ``origin``: (x, y) of the DEM's top-left corner (a Grid's x_left, y_top), so the bounds come out in its
    CRS; the default gives metres from that corner (y negative southwards). A quad belongs to the tile of its
    north-west corner, so the tiles' surface and planar areas add up to the whole DEM's.
    """
    _check_dem(dem)
    _check_gsd(gsd)
    if not (math.isfinite(tile_m) and tile_m > 0):
        raise ValueError(f"tile_stats: tile_m must be a positive number of metres; got {tile_m}")
    side = max(1, round(tile_m / gsd))
    height, width = dem.shape
    x0, y0 = origin
    out = []
    for r0 in range(0, height, side):
        r1 = min(height, r0 + side)
        for c0 in range(0, width, side):
            c1 = min(width, c0 + side)
            cells = dem[r0:r1, c0:c1]
            root_sum, triangles = _surface_sums(dem[r0:r1 + 1, c0:c1 + 1], gsd)  # quads starting in the tile
            heights = height_range(cells)
            out.append(TileStats(
                row=r0 // side,
                col=c0 // side,
                bounds=(x0 + c0 * gsd, y0 - r1 * gsd, x0 + c1 * gsd, y0 - r0 * gsd),
                valid_share=heights.valid / cells.size,
                rugosity=root_sum / triangles if triangles else math.nan,
                surface_m2=0.5 * gsd * gsd * root_sum,
                planar_m2=0.5 * gsd * gsd * triangles,
                heights=heights,
            ))
    return out


def hillshade(dem: np.ndarray, gsd: float, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
    """Shaded relief of ``dem`` ([H, W]) lit from ``azimuth`` (degrees clockwise from north) at ``altitude``
    (degrees above the horizon) → uint8 [H, W]: 0 where the height is NaN, else 1 + 254·max(cos i, 0) rounded,
    as GDAL's ``gdaldem hillshade``.

    cos i = (sin alt - p·sin az·cos alt - q·cos az·cos alt) / √(1 + p² + q²), the cosine between the surface
    normal (-p, -q, 1) and the light; p = ∂z/∂east, q = ∂z/∂north by Horn's 3x3 weights, metres on all three
    axes. A neighbour outside the DEM or without a height counts as the centre's height (GDAL's
    ``-compute_edges``), so edges and cells next to holes are shaded too. A flat DEM at altitude 45 gives 181.
    """
    _check_dem(dem)
    _check_gsd(gsd)
    height, width = dem.shape
    az, alt = math.radians(azimuth), math.radians(altitude)
    light_east, light_north, light_up = math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)
    out = np.zeros((height, width), dtype=np.uint8)
    step = _block_rows(width)
    for r0 in range(0, height, step):
        r1 = min(height, r0 + step)
        z = np.full((r1 - r0 + 2, width + 2), np.nan)  # the block with a one-cell halo
        lo, hi = max(0, r0 - 1), min(height, r1 + 1)
        z[lo - (r0 - 1):hi - (r0 - 1), 1:-1] = dem[lo:hi]
        centre = z[1:-1, 1:-1]
        nw, n, ne = (_neighbour(z, centre, -1, dc) for dc in (-1, 0, 1))
        w, e = _neighbour(z, centre, 0, -1), _neighbour(z, centre, 0, 1)
        sw, s, se = (_neighbour(z, centre, 1, dc) for dc in (-1, 0, 1))
        p = ((ne + 2 * e + se) - (nw + 2 * w + sw)) / (8 * gsd)  # ∂z/∂east
        q = ((nw + 2 * n + ne) - (sw + 2 * s + se)) / (8 * gsd)  # ∂z/∂north: row 0 is the north edge
        cos_i = (light_up - p * light_east - q * light_north) / np.sqrt(1 + p * p + q * q)
        shade = np.rint(1 + 254 * np.clip(cos_i, 0.0, 1.0))
        out[r0:r1] = np.where(np.isnan(centre), 0, shade).astype(np.uint8)
    return out


def _neighbour(z: np.ndarray, centre: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """The (dr, dc) neighbours of the inner cells of the haloed block ``z``, the centre's height where they have
    none."""
    n = z[1 + dr:z.shape[0] - 1 + dr, 1 + dc:z.shape[1] - 1 + dc]
    return np.where(np.isnan(n), centre, n)


def _surface_sums(dem: np.ndarray, gsd: float) -> tuple[float, int]:
    """(Σ √(1 + p² + q²), number of triangles) over the valid quads of ``dem``, in row blocks that overlap by
    one row (each quad counted once, by its top row)."""
    _check_dem(dem)
    _check_gsd(gsd)
    height, width = dem.shape
    root_sum, triangles = 0.0, 0
    step = _block_rows(width)
    for r0 in range(0, height - 1, step):
        r1 = min(height - 1, r0 + step)  # quads with top rows r0 .. r1-1
        z = np.asarray(dem[r0:r1 + 1], dtype=np.float64)
        z00, z01, z10, z11 = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
        upper = np.sqrt(1 + ((z01 - z00) / gsd) ** 2 + ((z11 - z01) / gsd) ** 2)  # NaN where a corner is
        lower = np.sqrt(1 + ((z11 - z10) / gsd) ** 2 + ((z10 - z00) / gsd) ** 2)
        valid = ~np.isnan(upper) & ~np.isnan(lower)  # a triangle is NaN iff one of its corners is: ask both
        root_sum += float(upper[valid].sum()) + float(lower[valid].sum())
        triangles += 2 * int(valid.sum())
    return root_sum, triangles


def _percentile(counts: np.ndarray, n: int, low: float, high: float, q: float) -> float:
    """numpy's linear-interpolation percentile q of n values from their histogram over [low, high]: the k-th
    smallest value is placed uniformly within its bin (the smallest and largest exactly)."""
    if high == low:
        return low
    cumulative = np.cumsum(counts)
    width = (high - low) / counts.size

    def order_statistic(k: int) -> float:
        if k == 0:
            return low
        if k == n - 1:
            return high
        b = int(np.searchsorted(cumulative, k, side="right"))  # the bin holding the k-th (0-based) value
        before = int(cumulative[b - 1]) if b else 0
        return low + (b + (k - before + 0.5) / int(counts[b])) * width

    h = (n - 1) * q / 100.0
    k = math.floor(h)
    lower = order_statistic(k)
    return lower if k + 1 >= n else lower + (h - k) * (order_statistic(k + 1) - lower)


def _row_blocks(dem: np.ndarray):
    """``dem`` as float64 row blocks of about :data:`_BLOCK_CELLS` cells."""
    step = _block_rows(dem.shape[1])
    for r0 in range(0, dem.shape[0], step):
        yield np.asarray(dem[r0:r0 + step], dtype=np.float64)


def _block_rows(width: int) -> int:
    return max(1, _BLOCK_CELLS // max(1, width))


def _check_dem(dem: np.ndarray) -> None:
    if not isinstance(dem, np.ndarray) or dem.ndim != 2 or not np.issubdtype(dem.dtype, np.floating):
        raise ValueError(f"expected a float DEM [H, W] (NaN = no data); got {getattr(dem, 'dtype', type(dem))} "
                         f"{np.shape(dem)}")


def _check_gsd(gsd: float) -> None:
    if not (math.isfinite(gsd) and gsd > 0):
        raise ValueError(f"gsd must be a positive number of metres per cell; got {gsd}")
