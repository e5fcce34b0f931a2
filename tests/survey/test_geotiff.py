"""pipeline.survey.geotiff: the grid's geometry, COGs read back with rasterio (CRS, transform, mask / nodata,
overviews, pixels), the validator, bounded memory, previews."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
import rasterio

from pipeline.scene.images import read_pixels
from pipeline.survey.geotiff import (
    CRS_TAG,
    LOCAL_FRAME_NAME,
    PREVIEW_NODATA_GREY,
    Grid,
    validate_cog,
    write_cog,
    write_preview,
)

UTM = Grid(x_left=350_000.0, y_top=8_100_000.0, gsd=0.05, width=600, height=400, crs=32754,
           crs_name="WGS 84 / UTM zone 54S")
LOCAL = Grid(x_left=-12.5, y_top=7.25, gsd=0.02, width=600, height=400, crs=None, crs_name=LOCAL_FRAME_NAME)


def _smooth_rgb(height: int, width: int) -> np.ndarray:
    """A smooth colour field (JPEG's friendly case, like an orthomosaic's sand and reef).  # [H, W, 3] uint8"""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    r = 128 + 100 * np.sin(x / 37.0)
    g = 128 + 90 * np.cos(y / 29.0)
    b = 60 + 0.25 * x + 0.2 * y
    return np.clip(np.stack([r, g, b], axis=2), 0, 255).astype(np.uint8)


def _footprint(height: int, width: int) -> np.ndarray:
    """An elliptic survey footprint: True inside.  # [H, W] bool"""
    y, x = np.mgrid[0:height, 0:width]
    return ((x - width / 2) / (0.45 * width)) ** 2 + ((y - height / 2) / (0.45 * height)) ** 2 <= 1.0


def test_grid_transform_centres_and_cells():
    t = UTM.transform()
    assert t @ (0, 0) == (UTM.x_left, UTM.y_top)
    assert t @ (600, 400) == pytest.approx((350_030.0, 8_099_980.0))  # north-up: y falls down the rows
    assert UTM.bounds() == pytest.approx((350_000.0, 8_099_980.0, 350_030.0, 8_100_000.0))
    x, y = UTM.cell_centre(0, 0)
    assert (x, y) == pytest.approx((350_000.025, 8_099_999.975))
    rows, cols = np.mgrid[0:400:7, 0:600:11]
    xs, ys = UTM.cell_centre(rows, cols)
    assert np.array_equal(xs, (t @ (cols + 0.5, rows + 0.5))[0])
    back_r, back_c = UTM.cell_at(xs, ys)
    assert np.array_equal(back_r, rows) and np.array_equal(back_c, cols)
    assert UTM.cell_at(UTM.x_left - 0.01, UTM.y_top + 0.01) == (-1, -1)  # outside: the caller's to check


@pytest.mark.parametrize("bad", [{"gsd": 0.0}, {"gsd": math.nan}, {"width": 0}, {"height": 2.5}, {"crs": -4326}])
def test_grid_rejects_nonsense(bad):
    fields = {"x_left": 0.0, "y_top": 0.0, "gsd": 0.1, "width": 4, "height": 4, "crs": None, "crs_name": "x"}
    with pytest.raises(ValueError):
        Grid(**(fields | bad))


def test_rgb_deflate_cog_in_utm_round_trips_exactly(tmp_path):
    rgb, valid = _smooth_rgb(400, 600), _footprint(400, 600)
    path = write_cog(tmp_path / "ortho.tif", rgb, UTM, mask=valid)
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32754
        assert src.transform == UTM.transform()
        assert (src.width, src.height, src.count, src.dtypes[0]) == (600, 400, 3, "uint8")
        assert src.nodata is None
        assert src.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]
        assert np.array_equal(src.read_masks(1) > 0, valid)
        assert src.overviews(1) == [2]
        assert src.compression == rasterio.enums.Compression.deflate
        assert src.tags()[CRS_TAG] == "WGS 84 / UTM zone 54S"
        assert np.array_equal(np.moveaxis(src.read(), 0, 2), rgb)
    assert validate_cog(path) == (True, [], [])


def test_rgb_jpeg_cog_keeps_the_mask_and_the_colours_within_tolerance(tmp_path):
    rgb, valid = _smooth_rgb(400, 600), _footprint(400, 600)
    path = write_cog(tmp_path / "ortho_web.tif", rgb, UTM, mask=valid, compress="JPEG", jpeg_quality=90)
    with rasterio.open(path) as src:
        assert src.tags(ns="IMAGE_STRUCTURE")["COMPRESSION"] == "YCbCr JPEG"
        assert np.array_equal(src.read_masks(1) > 0, valid)  # the mask is lossless even when the pixels are not
        error = np.abs(np.moveaxis(src.read(), 0, 2).astype(np.int16) - rgb)[valid]
    # Quality 90 on a smooth field with 4:2:0 chroma: measured 0.8 levels on average, 6 at worst; twice that
    # leaves room for another libjpeg build's rounding.
    assert error.mean() < 1.6 and error.max() <= 12
    assert validate_cog(path)[0]


def test_dem_with_nan_nodata_in_the_local_frame(tmp_path):
    y, x = np.mgrid[0:400, 0:600]
    dem = (0.3 * np.sin(x / 40.0) * np.cos(y / 25.0) + 0.001 * x).astype(np.float32)
    dem[~_footprint(400, 600)] = np.nan
    path = write_cog(tmp_path / "dem.tif", dem, LOCAL, nodata=math.nan)
    with rasterio.open(path) as src:
        assert src.crs is not None and src.crs.to_epsg() is None  # engineering CRS: no place on the Earth
        assert "LOCAL_CS" in src.crs.to_wkt() and LOCAL_FRAME_NAME in src.crs.to_wkt()
        assert src.crs.units_factor == ("metre", 1.0)
        assert src.transform == LOCAL.transform()
        assert src.dtypes[0] == "float32" and math.isnan(src.nodata)
        assert src.overviews(1) == [2]
        assert src.tags()[CRS_TAG] == LOCAL_FRAME_NAME
        back = src.read(1)
        overview = src.read(1, out_shape=(200, 300))  # the 1/2 level, averaged over valid cells only
    assert np.array_equal(back, dem, equal_nan=True)
    assert np.isfinite(overview).sum() > 0.5 * np.isfinite(dem).sum() / 4
    assert np.nanmax(np.abs(overview)) <= np.nanmax(np.abs(dem)) + 1e-6  # no nodata value averaged in
    assert validate_cog(path) == (True, [], [])


def test_memmap_input_is_written_a_row_of_blocks_at_a_time(tmp_path):
    """The writer never holds more than about one row of blocks beyond its input: numpy's peak allocation while
    writing a 4.7 MB memmap with 64-pixel blocks (0.3 MB rows) measured 0.3 MB; the array materialised: 6.9 MB."""
    height, width = 1024, 1536
    data = np.lib.format.open_memmap(tmp_path / "big.npy", mode="w+", dtype=np.uint8, shape=(height, width, 3))
    data[:] = _smooth_rgb(height, width)
    data.flush()
    valid = np.ones((height, width), dtype=bool)
    valid[:, :100] = False
    grid = Grid(0.0, 0.0, 0.1, width, height, None, LOCAL_FRAME_NAME)
    source = np.load(tmp_path / "big.npy", mmap_mode="r")
    write_cog(tmp_path / "warm.tif", source[:64, :64], Grid(0.0, 0.0, 0.1, 64, 64, None, "x"))  # one-off set-up
    block_row = 64 * width * 3
    tracemalloc.start()
    try:
        write_cog(tmp_path / "big.tif", source, grid, mask=valid, blocksize=64)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * block_row, f"peak {peak / 1e6:.2f} MB; a row of blocks is {block_row / 1e6:.2f} MB"
    with rasterio.open(tmp_path / "big.tif") as src:
        assert np.array_equal(np.moveaxis(src.read(), 0, 2), data)
        assert np.array_equal(src.read_masks(1) > 0, valid)
        assert src.overviews(1) == [2, 4, 8, 16, 32]  # halved while wider than a 64-pixel block
    assert validate_cog(tmp_path / "big.tif")[0]


def test_validate_cog_rejects_a_plain_striped_tiff(tmp_path):
    path = tmp_path / "plain.tif"
    with rasterio.open(path, "w", driver="GTiff", width=600, height=400, count=1, dtype="uint8",
                       crs="EPSG:32754", transform=UTM.transform()) as dst:
        dst.write(np.zeros((1, 400, 600), dtype=np.uint8))
    valid, errors, _ = validate_cog(path)
    assert not valid and errors


@pytest.mark.parametrize(
    ("array", "kwargs", "message"),
    [
        (np.zeros((400, 601, 3), np.uint8), {}, "got \\(400, 601, 3\\)"),
        (np.zeros((400, 600), np.float64), {}, "float64"),
        (np.zeros((400, 600), np.float32), {"nodata": math.nan, "mask": np.ones((400, 600), bool)}, "not both"),
        (np.zeros((400, 600), np.float32), {"compress": "JPEG"}, "JPEG"),
        (np.zeros((400, 600, 3), np.uint8), {"compress": "JPEG", "nodata": 0}, "mask instead"),
        (np.zeros((400, 600), np.uint8), {"nodata": 300}, "0..255"),
    ],
)
def test_write_cog_rejects_what_it_cannot_write(tmp_path, array, kwargs, message):
    with pytest.raises(ValueError, match=message):
        write_cog(tmp_path / "x.tif", array, UTM, **kwargs)
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_png_preview_is_small_and_transparent_where_there_is_no_data(tmp_path):
    rgb = np.zeros((400, 600, 3), dtype=np.uint8)
    rgb[:, :300] = (200, 40, 10)
    rgb[:, 300:] = (10, 90, 250)
    valid = np.ones((400, 600), dtype=bool)
    valid[:100] = False  # the top quarter
    px = read_pixels(write_preview(tmp_path / "p.png", rgb, max_side=100, mask=valid))
    assert px.shape == (67, 100, 4)  # k = 6: ceil(400 / 6) x ceil(600 / 6)
    assert np.all(px[:17, :, 3] == 0) and np.all(px[17:, :, 3] == 1)  # row 16 (input 96-101): 2 of 6 valid
    assert np.allclose(px[20:, :50, :3] * 255, (200, 40, 10)) and np.allclose(px[20:, 50:, :3] * 255, (10, 90, 250))


def test_jpeg_preview_shows_no_data_grey_and_averages_blocks(tmp_path):
    grey = np.zeros((90, 60), dtype=np.uint8)
    grey[:, 1::2] = 200  # stripes finer than the preview: their mean, not one of them
    valid = np.ones((90, 60), dtype=bool)
    valid[:, :30] = False
    px = read_pixels(write_preview(tmp_path / "p.jpg", grey, max_side=45, mask=valid))
    assert px.shape == (45, 30, 1)
    assert np.allclose(px[:, :12] * 255, PREVIEW_NODATA_GREY, atol=3)  # JPEG's ringing near the edge: a few levels
    assert np.allclose(px[:, 18:] * 255, 100, atol=3)


def test_preview_rejects_floats_and_unknown_formats(tmp_path):
    with pytest.raises(ValueError, match="uint8"):
        write_preview(tmp_path / "p.png", np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match=".png"):
        write_preview(tmp_path / "p.webp", np.zeros((4, 4), np.uint8))
