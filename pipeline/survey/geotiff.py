"""Cloud-Optimized GeoTIFFs of the survey products, and their small previews.

Every product is a raster on one regular north-up :class:`Grid`: square cells of ``gsd`` metres, the top-left
corner at (``x_left``, ``y_top``) in the CRS's metres, rows running south (y decreases down the rows). The CRS
is a UTM zone (EPSG 326xx / 327xx) when the survey is georeferenced; otherwise a local metric frame, written as
an engineering CRS (GeoTIFF "user-defined" LOCAL_CS, x east, y north, metres) so GIS tools still read metres
and never place the survey on the Earth. Either way the CRS's human name is also in the ``DUALPHYS_CRS`` tag.

What the files hold:

- orthomosaics (RGB uint8): DEFLATE with the horizontal predictor and an internal 1-bit mask (cells without
  data). Lossless, because the products are measured (colour of the de-watered mosaic against the one with
  water, classification), and a mask rather than a nodata colour, because any RGB triple can be a real pixel.
  ``compress="JPEG"`` (YCbCr, with the same mask) is there for a light web copy, several times smaller.
- rasters of values (DEM, confidence; float32): DEFLATE with the floating-point predictor, nodata NaN: the
  in-memory convention of :mod:`pipeline.survey.terrain`, no sentinel that a careless reader could average in
  as a height (a stray NaN shows), and GDAL, QGIS and rasterio honour a NaN nodata.
- overviews: made by GDAL's COG driver (halving until a level fits one block) with AVERAGE resampling, which
  skips masked and nodata cells.

Large rasters are written in bounded memory: the array (a numpy memmap is fine) is copied one row of blocks
at a time into a tiled GeoTIFF in a temporary folder beside the output, and GDAL's COG driver (which needs a
whole source dataset) turns that into the COG; the result is renamed into place, so a reader never sees half a
file.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.crs import CRS
from rasterio.transform import Affine
from rasterio.windows import Window
from rio_cogeo.cogeo import cog_validate

from pipeline.scene.images import write_image

log = logging.getLogger(__name__)

LOCAL_FRAME_NAME = "local metric frame (not georeferenced)"
CRS_TAG = "DUALPHYS_CRS"  # the dataset tag holding Grid.crs_name
PREVIEW_NODATA_GREY = 128  # what a JPEG preview shows where there is no data (PNG previews are transparent there)
_PREVIEW_BLOCK_VALUES = 1 << 24  # input values averaged per step of write_preview (~128 MB as float64)


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid of square cells: cell (row, col) covers x in [x_left + col·gsd, x_left + (col+1)·gsd]
    and y in [y_top - (row+1)·gsd, y_top - row·gsd], metres in the CRS."""

    x_left: float
    """x of the grid's left edge (easting in UTM), metres."""
    y_top: float
    """y of the grid's top edge (northing in UTM), metres."""
    gsd: float
    """Cell size, metres per pixel (square cells)."""
    width: int
    """Columns."""
    height: int
    """Rows."""
    crs: int | None
    """EPSG code (a UTM zone: 326xx north, 327xx south), or None for the local metric frame."""
    crs_name: str
    """Human name of the CRS, e.g. "WGS 84 / UTM zone 54S" or :data:`LOCAL_FRAME_NAME`."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gsd) and self.gsd > 0):
            raise ValueError(f"Grid.gsd must be a positive number of metres; got {self.gsd}")
        if not (math.isfinite(self.x_left) and math.isfinite(self.y_top)):
            raise ValueError(f"Grid origin must be finite; got ({self.x_left}, {self.y_top})")
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise ValueError(f"Grid size must be positive integers; got {self.width} x {self.height}")
        if self.crs is not None and (int(self.crs) != self.crs or self.crs <= 0):
            raise ValueError(f"Grid.crs must be an EPSG code or None; got {self.crs!r}")

    def transform(self) -> Affine:
        """The rasterio/GDAL affine transform: (col, row) of a cell corner → (x, y)."""
        return Affine(self.gsd, 0.0, self.x_left, 0.0, -self.gsd, self.y_top)

    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) in metres."""
        return (self.x_left, self.y_top - self.height * self.gsd, self.x_left + self.width * self.gsd, self.y_top)

    def cell_centre(self, row, col):
        """(x, y) of the centre of cell (row, col); scalars or arrays of any matching shape."""
        return self.x_left + (np.asarray(col) + 0.5) * self.gsd, self.y_top - (np.asarray(row) + 0.5) * self.gsd

    def cell_at(self, x, y):
        """(row, col) of the cell holding (x, y), as int64 (scalars or arrays); may lie outside the grid, the
        caller checks against ``height`` / ``width``."""
        row = np.floor((self.y_top - np.asarray(y, dtype=np.float64)) / self.gsd).astype(np.int64)
        col = np.floor((np.asarray(x, dtype=np.float64) - self.x_left) / self.gsd).astype(np.int64)
        return row, col


def write_cog(
    path: str | os.PathLike[str],
    array: np.ndarray,
    grid: Grid,
    nodata: float | None = None,
    mask: np.ndarray | None = None,
    *,
    compress: Literal["DEFLATE", "JPEG"] = "DEFLATE",
    jpeg_quality: int = 90,
    blocksize: int = 512,
    tags: dict[str, str] | None = None,
) -> Path:
    """Write ``array`` ([H, W] or [H, W, C], uint8 or float32, H, W = grid.height, grid.width) as a COG.

    ``nodata``: the value marking cells without data in ``array`` itself (NaN for float rasters). ``mask``:
    [H, W] bool, True where there is data, written as the file's internal mask (use it for RGB). At most one
    of the two. ``compress``: "DEFLATE" (lossless) or "JPEG" (uint8, 1 or 3 bands, ``jpeg_quality``; needs a
    mask rather than nodata). ``blocksize``: the COG's tile side. ``tags``: extra dataset tags. Either may be
    a numpy memmap: they are read one row of blocks at a time. Returns the path.
    """
    path = Path(path)
    _check_raster(array, grid, nodata, mask, compress)
    count = 1 if array.ndim == 2 else array.shape[2]
    if blocksize < 16 or blocksize % 16:
        raise ValueError(f"write_cog: blocksize must be a positive multiple of 16; got {blocksize}")
    profile = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": count,
        "dtype": array.dtype.name,
        "crs": _crs(grid),
        "transform": grid.transform(),
        "nodata": nodata,
        "tiled": True,
        "blockxsize": blocksize,
        "blockysize": blocksize,
        "compress": "deflate",
        "zlevel": 1,  # the staging file lives for seconds: fast beats small
        "bigtiff": "IF_SAFER",
    }
    cog_options = {
        "compress": compress,
        "blocksize": blocksize,
        "overview_resampling": "AVERAGE",
        "bigtiff": "IF_SAFER",
    }
    if compress == "JPEG":
        cog_options["quality"] = int(jpeg_quality)
    else:
        cog_options["predictor"] = "YES"  # GDAL picks horizontal differencing for integers, floating-point for floats
    path.parent.mkdir(parents=True, exist_ok=True)
    with (
        tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.stem}.") as tmp,
        rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True),
    ):
        stage = Path(tmp) / "stage.tif"
        with rasterio.open(stage, "w", **profile) as dst:
            dst.update_tags(**{CRS_TAG: grid.crs_name, **(tags or {})})
            for r0 in range(0, grid.height, blocksize):
                r1 = min(grid.height, r0 + blocksize)
                window = Window(0, r0, grid.width, r1 - r0)
                block = np.asarray(array[r0:r1])  # [h, W] or [h, W, C]: one row of blocks, read from a memmap
                dst.write(block[None] if block.ndim == 2 else np.moveaxis(block, 2, 0), window=window)
                if mask is not None:
                    dst.write_mask(np.asarray(mask[r0:r1], dtype=bool).astype(np.uint8) * np.uint8(255), window=window)
        out = Path(tmp) / "out.tif"
        rasterio.shutil.copy(stage, out, driver="COG", **cog_options)
        os.replace(out, path)
    log.info("wrote %s: %d x %d x %d %s, %s, %s, %.1f MB", path, grid.width, grid.height, count,
             array.dtype.name, compress, grid.crs_name, path.stat().st_size / 1e6)
    return path


def validate_cog(path: str | os.PathLike[str]) -> tuple[bool, list[str], list[str]]:
    """(valid, errors, warnings) of rio-cogeo's COG validation of the file at ``path``."""
    valid, errors, warnings = cog_validate(str(path), quiet=True)
    for w in warnings:
        log.warning("%s: COG warning: %s", path, w)
    return bool(valid), list(errors), list(warnings)


def write_preview(
    path: str | os.PathLike[str],
    array: np.ndarray,
    max_side: int = 2048,
    mask: np.ndarray | None = None,
) -> Path:
    """A downsized picture of a uint8 raster ([H, W] or [H, W, 3]) whose longer side is at most ``max_side``.

    The format follows the suffix: .jpg/.jpeg (cells without data mid-grey, :data:`PREVIEW_NODATA_GREY`) or
    .png (transparent there). ``mask``: [H, W] bool, True where there is data (None: everywhere). Each preview
    pixel is the mean of the valid cells of a k x k block (k the smallest integer that fits ``max_side``), and
    has no data when fewer than half its block's cells have; read a row of blocks at a time (memmaps welcome).
    Returns the path.
    """
    path = Path(path)
    a = np.asarray(array)  # a memmap stays on disk: no copy
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3) or 0 in a.shape[:2]:
        raise ValueError(f"write_preview expects uint8 [H, W] or [H, W, 3]; got {a.dtype} {a.shape}")
    if mask is not None and np.shape(mask) != a.shape[:2]:
        raise ValueError(f"write_preview: mask must be [H, W] = {a.shape[:2]}; got {np.shape(mask)}")
    if max_side < 1:
        raise ValueError(f"write_preview: max_side must be >= 1; got {max_side}")
    suffix = path.suffix.lower()
    if suffix not in (".jpg", ".jpeg", ".png"):
        raise ValueError(f"write_preview: use a .jpg, .jpeg or .png name; got {path.name}")
    k = max(1, math.ceil(max(a.shape[:2]) / max_side))
    mean, valid = _block_mean(a, mask, k)  # [h, w, C] float64, [h, w] bool
    pixels = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    if suffix == ".png":
        rgb = pixels if pixels.shape[2] == 3 else np.repeat(pixels, 3, axis=2)
        image = np.concatenate([rgb, np.where(valid, 255, 0).astype(np.uint8)[..., None]], axis=2)  # [h, w, 4]
    else:
        image = np.where(valid[..., None], pixels, np.uint8(PREVIEW_NODATA_GREY))
    write_image(path, image[..., 0] if image.shape[2] == 1 else image, quality=90)
    log.info("wrote preview %s: %d x %d (1/%d)", path, image.shape[1], image.shape[0], k)
    return path


def _check_raster(array: np.ndarray, grid: Grid, nodata: float | None, mask: np.ndarray | None,
                  compress: str) -> None:
    shape = np.shape(array)
    if len(shape) not in (2, 3) or shape[:2] != (grid.height, grid.width) or (len(shape) == 3 and shape[2] < 1):
        raise ValueError(f"write_cog expects [H, W] or [H, W, C] with H, W = {grid.height}, {grid.width}; "
                         f"got {shape}")
    if array.dtype not in (np.uint8, np.float32):
        raise ValueError(f"write_cog writes uint8 or float32 rasters; got {array.dtype}")
    if nodata is not None and mask is not None:
        raise ValueError("write_cog: give nodata or mask, not both")
    if mask is not None and np.shape(mask) != shape[:2]:
        raise ValueError(f"write_cog: mask must be [H, W] = {shape[:2]}; got {np.shape(mask)}")
    if nodata is not None and array.dtype == np.uint8 and not (float(nodata).is_integer() and 0 <= nodata <= 255):
        raise ValueError(f"write_cog: nodata of a uint8 raster must be an integer in 0..255; got {nodata}")
    if compress not in ("DEFLATE", "JPEG"):
        raise ValueError(f"write_cog: compress must be 'DEFLATE' or 'JPEG'; got {compress!r}")
    if compress == "JPEG" and (array.dtype != np.uint8 or (len(shape) == 3 and shape[2] not in (1, 3))):
        raise ValueError(f"write_cog: JPEG holds uint8 with 1 or 3 bands; got {array.dtype} {shape}")
    if compress == "JPEG" and nodata is not None:
        raise ValueError("write_cog: JPEG blurs a nodata value into its neighbours; give a mask instead")


def _crs(grid: Grid) -> CRS:
    if grid.crs is not None:
        return CRS.from_epsg(grid.crs)
    # The local frame: an engineering CRS (no datum on the Earth), x east and y north in metres. GDAL writes it
    # to GeoTIFF as a user-defined model with metre units, and reads it back as the same LOCAL_CS.
    name = grid.crs_name.replace('"', "'")
    return CRS.from_wkt(f'LOCAL_CS["{name}",LOCAL_DATUM["survey frame",32767],UNIT["metre",1],'
                        'AXIS["Easting",EAST],AXIS["Northing",NORTH]]')


def _block_mean(array: np.ndarray, mask: np.ndarray | None, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of the valid cells of each k x k block of ``array`` ([H, W] or [H, W, C]) → ([h, w, C] float64,
    [h, w] bool: at least half the block's cells valid), h, w = ceil(H / k), ceil(W / k)."""
    height, width = array.shape[:2]
    channels = 1 if array.ndim == 2 else array.shape[2]
    out_h, out_w = -(-height // k), -(-width // k)
    mean = np.zeros((out_h, out_w, channels))
    valid = np.zeros((out_h, out_w), dtype=bool)
    step = max(1, _PREVIEW_BLOCK_VALUES // (k * k * out_w * channels))  # output rows per step
    for o0 in range(0, out_h, step):
        o1 = min(out_h, o0 + step)
        r0, r1 = o0 * k, min(height, o1 * k)
        pad = ((0, (o1 - o0) * k - (r1 - r0)), (0, out_w * k - width))
        values = np.pad(np.asarray(array[r0:r1], dtype=np.float64).reshape(r1 - r0, width, channels), pad + ((0, 0),))
        inside = np.pad(np.ones((r1 - r0, width), dtype=bool), pad)  # False on the padding
        good = inside if mask is None else np.pad(np.asarray(mask[r0:r1], dtype=bool), pad)
        blocks = (o1 - o0, k, out_w, k)
        sums = (values * good[..., None]).reshape(*blocks, channels).sum(axis=(1, 3))
        n_good = good.reshape(blocks).sum(axis=(1, 3))
        n_inside = inside.reshape(blocks).sum(axis=(1, 3))
        mean[o0:o1] = sums / np.maximum(n_good, 1)[..., None]
        valid[o0:o1] = 2 * n_good >= n_inside
    return mean, valid
