"""pipeline.survey.terrain against closed forms (planes), a numerical integral (a sinusoidal reef), numpy's own
statistics, and itself across row blocks and tiles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.survey import terrain
from pipeline.survey.terrain import HeightRange, height_range, hillshade, rugosity, tile_stats

GSD = 0.05


def _plane(height: int, width: int, a: float, b: float, gsd: float = GSD) -> np.ndarray:
    """z = a·east + b·north at the cell centres of a north-up grid (row 0 the north edge).  # [H, W] float64"""
    row, col = np.mgrid[0:height, 0:width].astype(np.float64)
    return a * col * gsd - b * row * gsd


def _reef(height: int, width: int) -> np.ndarray:
    """Heights with NaN holes and a ragged footprint, like a survey's DEM.  # [H, W] float32"""
    rng = np.random.default_rng(7)
    row, col = np.mgrid[0:height, 0:width]
    z = 0.4 * np.sin(col / 9.0) * np.cos(row / 13.0) + 0.002 * col + 0.05 * rng.standard_normal((height, width))
    z[(col - width / 2) ** 2 / (0.5 * width) ** 2 + (row - height / 2) ** 2 / (0.45 * height) ** 2 > 1] = np.nan
    z[rng.random((height, width)) < 0.03] = np.nan
    return z.astype(np.float32)


def test_flat_dem_has_rugosity_one():
    assert rugosity(np.full((40, 60), 3.7, dtype=np.float32), GSD) == 1.0


@pytest.mark.parametrize(("a", "b"), [(0.5, 0.0), (0.0, -2.0), (0.3, 0.4)])
def test_tilted_plane_has_rugosity_secant_of_its_slope(a, b):
    # Every triangle of a plane is exact: √(1 + a² + b²), the plane's area over its footprint.
    assert rugosity(_plane(30, 50, a, b), GSD) == pytest.approx(math.sqrt(1 + a * a + b * b), abs=1e-9)


def test_sinusoidal_reef_matches_the_surface_integral():
    """z = A·sin(kx)·cos(ky) over whole wavelengths: the surface over the footprint is the mean of
    √(1 + z_x² + z_y²) over one period, by the midpoint rule (spectrally accurate for a smooth periodic
    integrand: 400 and 2000 points per wavelength agree to 16 digits)."""
    amplitude, wavelength = 0.25, 1.0  # slopes up to A·k = 1.57: a rough reef
    k = 2 * math.pi / wavelength
    n = 200  # DEM samples over 10 wavelengths: 20 per wavelength
    gsd = 10 * wavelength / n
    x = np.arange(n + 1) * gsd  # the quads span exactly [0, 10 λ]
    xx, yy = np.meshgrid(x, x)
    dem = (amplitude * np.sin(k * xx) * np.cos(k * yy)).astype(np.float32)
    fine = (np.arange(400) + 0.5) * (wavelength / 400)  # one wavelength, midpoints
    fx, fy = np.meshgrid(fine, fine)
    zx = amplitude * k * np.cos(k * fx) * np.cos(k * fy)
    zy = -amplitude * k * np.sin(k * fx) * np.sin(k * fy)
    expected = float(np.mean(np.sqrt(1 + zx**2 + zy**2)))
    assert expected > 1.3  # a surface rough enough that a wrong area formula shows
    # The triangles cut the crests: measured 0.27 % low at 20 samples per wavelength (1.06 % at 10, 0.07 % at 40).
    assert rugosity(dem, gsd) == pytest.approx(expected, rel=0.01)


def test_rugosity_counts_only_quads_with_four_heights():
    dem = _plane(20, 20, 1.0, 0.0)
    dem[:, 10:] = 0.0  # a flat half ...
    dem[:, 9] = np.nan  # ... cut off from the tilted half: no quad spans the seam
    assert rugosity(dem, GSD) == pytest.approx((8 * math.sqrt(2) + 9 * 1.0) / 17, abs=1e-12)
    assert math.isnan(rugosity(np.full((5, 5), np.nan), GSD))
    assert math.isnan(rugosity(np.zeros((1, 5)), GSD))  # one row: no quads


def test_height_range_matches_numpy():
    dem = _reef(300, 400)
    r = height_range(dem)
    z = dem[~np.isnan(dem)].astype(np.float64)
    assert r.valid == z.size
    assert (r.min, r.max) == (z.min(), z.max())
    assert r.mean == pytest.approx(z.mean(), rel=1e-12) and r.std == pytest.approx(z.std(), rel=1e-12)
    assert (r.p2, r.p98) == tuple(np.percentile(z, [2, 98]))
    assert r.robust_range == r.p98 - r.p2
    assert r.p98 - r.p2 < r.max - r.min


def test_height_range_of_a_large_dem_reads_percentiles_from_a_histogram(monkeypatch):
    dem = _reef(300, 400)
    z = dem[~np.isnan(dem)].astype(np.float64)
    monkeypatch.setattr(terrain, "_BLOCK_CELLS", 5000)  # as if the DEM were larger than a block: the histogram
    r = height_range(dem)
    bin_width = (z.max() - z.min()) / 2**20  # its resolution
    p2, p98 = np.percentile(z, [2, 98])
    assert 0 < abs(r.p2 - p2) <= bin_width and 0 < abs(r.p98 - p98) <= bin_width  # close, and not the exact path
    assert (r.valid, r.min, r.max) == (z.size, z.min(), z.max())
    assert r.mean == pytest.approx(z.mean(), rel=1e-12) and r.std == pytest.approx(z.std(), rel=1e-12)


def test_height_range_of_a_constant_and_of_nothing():
    assert height_range(np.full((3, 4), -2.5, np.float32)) == HeightRange(12, -2.5, -2.5, -2.5, -2.5, 0.0, -2.5, 0.0)
    empty = height_range(np.full((3, 4), np.nan, np.float32))
    assert empty.valid == 0 and math.isnan(empty.mean) and math.isnan(empty.robust_range)


def test_row_blocks_change_nothing(monkeypatch):
    """The same numbers whether the DEM is read in one block or in blocks of 7 rows (an odd split that leaves
    quads and hillshade windows straddling block edges)."""
    dem = _reef(90, 120)
    whole = rugosity(dem, GSD), height_range(dem), hillshade(dem, GSD)
    monkeypatch.setattr(terrain, "_BLOCK_CELLS", 7 * 120)
    blocked = rugosity(dem, GSD), height_range(dem), hillshade(dem, GSD)
    assert blocked[0] == pytest.approx(whole[0], rel=1e-14)
    assert (blocked[1].valid, blocked[1].min, blocked[1].max) == (whole[1].valid, whole[1].min, whole[1].max)
    assert blocked[1].mean == pytest.approx(whole[1].mean, rel=1e-12)
    assert np.array_equal(blocked[2], whole[2])


def test_tile_stats_cover_the_dem_and_add_up():
    dem = _reef(100, 150)
    dem[:30, :30] = np.nan  # the first tile saw nothing
    origin = (350_000.0, 8_100_000.0)
    tiles = tile_stats(dem, GSD, tile_m=1.5, origin=origin)  # 30-cell tiles: 4 x 5, the last row 10 cells tall
    assert [(t.row, t.col) for t in tiles] == [(r, c) for r in range(4) for c in range(5)]
    assert tiles[0].bounds == pytest.approx((350_000.0, 8_099_998.5, 350_001.5, 8_100_000.0))
    assert tiles[-1].bounds == pytest.approx((350_006.0, 8_099_995.0, 350_007.5, 8_099_995.5))
    for t in tiles:
        r0, c0 = 30 * t.row, 30 * t.col
        cells = dem[r0:r0 + 30, c0:c0 + 30]
        assert t.valid_share == pytest.approx(np.isfinite(cells).mean())
        assert t.heights == height_range(cells)
    # Quads belong to the tile of their north-west corner: the tiles' areas are the DEM's.
    surface, planar = sum(t.surface_m2 for t in tiles), sum(t.planar_m2 for t in tiles)
    assert surface / planar == pytest.approx(rugosity(dem, GSD), rel=1e-12)
    corner = tiles[0]
    assert corner.valid_share == 0 and corner.planar_m2 == 0 and math.isnan(corner.rugosity)


def test_tile_of_a_plane_has_the_plane_rugosity():
    tiles = tile_stats(_plane(40, 40, 0.75, 0.0), GSD, tile_m=1.0)
    assert len(tiles) == 4 and all(t.rugosity == pytest.approx(1.25, abs=1e-9) for t in tiles)
    assert tiles[3].bounds == pytest.approx((1.0, -2.0, 2.0, -1.0))  # default origin: metres from the top-left


def _expected_shade(p: float, q: float, azimuth: float, altitude: float) -> int:
    """The closed form: the plane's unit normal ∝ (-p, -q, 1) against the unit vector towards the light."""
    az, alt = math.radians(azimuth), math.radians(altitude)
    normal = np.array([-p, -q, 1.0]) / math.sqrt(1 + p * p + q * q)
    light = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])  # east, north, up
    return int(round(1 + 254 * max(0.0, float(normal @ light))))


@pytest.mark.parametrize(
    ("a", "b", "azimuth", "altitude"),
    [(0.0, 0.0, 315, 45), (0.6, -0.3, 315, 45), (-0.8, 0.2, 315, 45), (0.4, 0.4, 90, 30), (2.0, 0.0, 270, 20)],
)
def test_hillshade_of_a_plane_is_the_closed_form(a, b, azimuth, altitude):
    shade = hillshade(_plane(12, 15, a, b), GSD, azimuth, altitude)
    assert shade.dtype == np.uint8 and shade.shape == (12, 15)
    assert np.all(shade[1:-1, 1:-1] == _expected_shade(a, b, azimuth, altitude))


def test_hillshade_lights_slopes_facing_the_sun():
    flat = hillshade(_plane(5, 5, 0.0, 0.0), GSD)[2, 2]
    assert flat == 181  # gdaldem's value for flat ground at altitude 45: 1 + 254·sin 45°
    # z = a·east + b·north faces the way it falls: its normal is (-a, -b, 1).
    faces_north_west = hillshade(_plane(5, 5, 0.5, -0.5), GSD)[2, 2]  # rises to the south-east: towards a 315° sun
    faces_south_east = hillshade(_plane(5, 5, -0.5, 0.5), GSD)[2, 2]
    assert faces_north_west > flat > faces_south_east
    assert hillshade(_plane(5, 5, 0.0, 10.0), GSD, azimuth=0, altitude=10)[2, 2] == 1  # a cliff in its own shadow


def test_hillshade_marks_holes_zero_and_shades_their_rims_and_edges():
    dem = _plane(20, 20, 0.3, 0.1)
    dem[8:11, 8:11] = np.nan
    shade = hillshade(dem, GSD)
    assert np.all(shade[8:11, 8:11] == 0)
    assert np.count_nonzero(shade) == 20 * 20 - 9  # the hole's rim and the DEM's border are shaded too
    # On a plane, the centre's height stands in for a missing neighbour: the rim's slope is halved or so, not lost.
    assert np.all(np.abs(shade[7, 7:12].astype(int) - _expected_shade(0.3, 0.1, 315, 45)) < 20)


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.int16), np.zeros((4, 4, 1), np.float32), [[0.0, 1.0]]])
def test_terrain_rejects_what_is_not_a_dem(bad):
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        rugosity(bad, GSD)
    with pytest.raises(ValueError, match="gsd"):
        hillshade(np.zeros((4, 4), np.float32), 0.0)
