"""Image files in and out, through OpenImageIO (imported lazily, inside the functions).

Pixels in memory are ``float32 [H, W, 3]`` in [0, 1], already in display orientation (EXIF ``Orientation``
applied). The format of a file is decided by its content, not its name: OIIO falls back to the plugin that
recognises the bytes, so a JPEG saved as ``.png`` reads (a real case in the U45 set).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# Image file names by lower-case suffix (matching is case-insensitive). The one place these lists are spelled.
JPEG_EXTENSIONS = frozenset({".jpg", ".jpeg"})
# What list_images picks up (SfM's and the loaders' input; ingest writes every photo as .jpg or .png).
IMAGE_EXTENSIONS = JPEG_EXTENSIONS | {".png", ".tif", ".tiff", ".bmp", ".webp", ".exr"}
# What counts as a photo in a survey folder: those and the further formats OpenImageIO decodes, which ingest
# converts to PNG.
DECODABLE_EXTENSIONS = IMAGE_EXTENSIONS | {".jp2", ".jxl", ".dpx", ".tga", ".ppm", ".pgm", ".hdr"}

_FLOAT_FORMATS = {".exr", ".tif", ".tiff"}  # may hold float32 pixels
# zlib level of every PNG the pipeline writes (renders, restored photos, confidence maps, report pictures): 3, not
# libpng's 6. A 320x240 render encodes 2.4x faster (8-bit 29 -> 12 ms, 16-bit 40 -> 21 ms) for files 4-6 % larger,
# still lossless; a 24-view fast job writes ~230 PNGs (docs/DECISIONS.md, "Whole-job speed").
PNG_COMPRESSION_LEVEL = 3
_16BIT_FORMATS = {".png", ".tif", ".tiff"}  # may hold uint16 pixels


class ImageReadError(Exception):
    """A file that is not a decodable image (missing, unknown format, truncated, ...)."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = Path(path)
        self.reason = reason.strip() or "unknown error"
        super().__init__(f"cannot read image {self.path}: {self.reason}")


def read_pixels(path: str | os.PathLike[str]) -> np.ndarray:
    """Decode an image file as stored, EXIF orientation applied.  # [H, W, C] float32

    Colour is returned as stored (alpha not premultiplied). Integer formats are scaled to [0, 1] (8-bit by
    255, 16-bit by 65535); float formats are returned as stored (no clipping); the channel count is the
    file's. Only the first subimage is read. A decoder error or warning (e.g. libjpeg's "Premature end of
    JPEG file" on a truncated download, which OIIO's ImageBuf would hide by filling grey) raises
    :class:`ImageReadError`.
    """
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    path = Path(path)
    if not path.is_file():
        raise ImageReadError(path, "no such file")
    hints = oiio.ImageSpec()
    hints.attribute("oiio:UnassociatedAlpha", 1)  # colour as stored: OIIO would premultiply PNG/TIFF alpha
    inp = oiio.ImageInput.open(str(path), hints)
    if inp is None:
        raise ImageReadError(path, _first_line(oiio.geterror()) or "unknown or unsupported image format")
    try:
        spec = inp.spec()
        orientation = spec.get_int_attribute("Orientation", 1)
        px = inp.read_image("float")
        err = inp.geterror()
    finally:
        inp.close()
    if px is None or err:
        raise ImageReadError(path, _first_line(err) or "decoding failed")
    px = np.asarray(px, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if orientation != 1:
        px = _reorient(px, orientation)
    return px


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a photo as RGB in [0, 1], EXIF orientation applied.  # [H, W, 3] float32

    8/16-bit and float files are accepted; grey (and grey + alpha) is replicated to three channels, alpha
    is dropped, float values are clipped to [0, 1]. Raises :class:`ImageReadError` naming the file when it
    cannot be decoded or has non-finite pixels.
    """
    px = read_pixels(path)
    c = px.shape[2]
    if c in (1, 2):
        px = np.repeat(px[:, :, :1], 3, axis=2)
    elif c >= 3:
        px = px[:, :, :3]
    else:  # pragma: no cover - OIIO never reports 0 channels for a decoded image
        raise ImageReadError(path, f"image has {c} channels")
    if not np.isfinite(px).all():
        raise ImageReadError(path, "image holds NaN or infinite values")
    return np.ascontiguousarray(np.clip(px, 0.0, 1.0), dtype=np.float32)


def image_orientation(path: str | os.PathLike[str]) -> int:
    """The EXIF orientation tag of a file (1 = as stored, also when absent or unreadable); header only."""
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()  # clear the pending message
        return 1
    try:
        return int(inp.spec().get_int_attribute("Orientation", 1))
    finally:
        inp.close()


def write_image(
    path: str | os.PathLike[str], arr: np.ndarray, *, bits: int | None = None, quality: int = 95
) -> Path:
    """Write ``arr`` ([H, W], [H, W, 1|3|4]) to ``path``; the format follows the extension.

    Bit depth: ``bits`` if given, else from the dtype — uint8 → 8, uint16 → 16, float → 32 for
    .exr/.tif/.tiff and 8 otherwise. Float data is clipped to [0, 1] before quantising. PNG takes 8/16,
    TIFF 8/16/32, EXR 32 (float32), JPEG 8 (``quality``). The file is written to a temporary name in the same
    folder and renamed, so a reader never sees half a file. Returns the path.
    """
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    path = Path(path)
    ext = path.suffix.lower()
    a = np.asarray(arr)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"write_image expects [H, W], [H, W, 1|3|4]; got shape {np.shape(arr)}")
    if bits is None:
        if a.dtype == np.uint8:
            bits = 8
        elif a.dtype == np.uint16:
            bits = 16
        else:
            bits = 32 if ext in _FLOAT_FORMATS else 8
    allowed = {
        ".png": {8, 16},
        ".jpg": {8},
        ".jpeg": {8},
        ".tif": {8, 16, 32},
        ".tiff": {8, 16, 32},
        ".exr": {32},
    }
    if ext not in allowed:
        raise ValueError(f"write_image: unsupported extension {ext!r} for {path} (use {sorted(allowed)})")
    if bits not in allowed[ext]:
        raise ValueError(
            f"write_image: {ext} cannot hold {bits}-bit pixels (allowed: {sorted(allowed[ext])})"
        )
    data, fmt = _quantise(a, bits)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # our colour is not premultiplied: store it unchanged
    if ext in JPEG_EXTENSIONS:
        if c == 4:
            raise ValueError(f"write_image: JPEG has no alpha channel ({path})")
        spec.attribute("Compression", f"jpeg:{int(quality)}")
    elif ext in (".exr", ".tif", ".tiff"):
        spec.attribute("Compression", "zip")
    elif ext == ".png":
        spec.attribute("png:compressionLevel", PNG_COMPRESSION_LEVEL)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise OSError(f"cannot write {path}: {_first_line(oiio.geterror())}")
    try:
        ok = out.open(str(tmp), spec) and out.write_image(data)
        err = out.geterror()
    finally:
        out.close()
    if not ok:
        tmp.unlink(missing_ok=True)
        raise OSError(f"cannot write {path}: {_first_line(err) or 'unknown error'}")
    os.replace(tmp, path)
    return path


def list_images(folder: str | os.PathLike[str]) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name (plain string order, like COLMAP and 3DGS).

    Known extensions (:data:`IMAGE_EXTENSIONS`, case-insensitive); hidden files (``.name``, including macOS
    ``._name`` resource forks) are ignored. The files are not opened here. Raises ``FileNotFoundError`` if
    ``folder`` is not a directory.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} does not exist")
    files = [
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS
    ]
    return sorted(files, key=lambda p: p.name)


def resize_area(img: np.ndarray, factor: float) -> np.ndarray:
    """Downscale by ``factor`` in (0, 1] with area averaging (antialiased).  # [H, W, C] -> [h, w, C]

    The output size is ``max(1, round(H * factor)) x max(1, round(W * factor))``, the same rounding as
    :meth:`~pipeline.scene.records.Camera.scaled`, so a scaled camera and a resized image always agree.
    """
    if not 0.0 < factor <= 1.0:
        raise ValueError(f"resize_area: factor must be in (0, 1], got {factor}")
    h, w = img.shape[:2]
    return resize_area_to(img, (max(1, round(h * factor)), max(1, round(w * factor))))


def resize_area_to(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-average ``img`` [H, W] or [H, W, C] down to ``size`` = (h, w) with h <= H, w <= W.

    Each output pixel is the mean of the input area it covers (fractional pixels weighted by overlap), i.e.
    a box prefilter of exactly the output pixel's footprint, done as two small matrix products.
    """
    h, w = size
    if img.ndim not in (2, 3):
        raise ValueError(f"resize_area_to expects [H, W] or [H, W, C]; got shape {img.shape}")
    H, W = img.shape[:2]
    if not (1 <= h <= H and 1 <= w <= W):
        raise ValueError(f"resize_area_to only downsizes: {H}x{W} -> {h}x{w}")
    if (h, w) == (H, W):
        return img.astype(np.float32, copy=True)
    x = img.astype(np.float32)
    Ay, Ax = _area_matrix(H, h), _area_matrix(W, w)  # [h, H], [w, W]
    out = np.einsum("yY,YX...->yX...", Ay, x)
    out = np.einsum("xX,yX...->yx...", Ax, out)
    return np.ascontiguousarray(out, dtype=np.float32)


def _area_matrix(n_in: int, n_out: int) -> np.ndarray:
    """Row i averages input cells over [i, i+1) * n_in / n_out (overlap-weighted).  # [n_out, n_in]"""
    s = n_in / n_out
    lo = np.arange(n_out)[:, None] * s  # [n_out, 1]
    cells = np.arange(n_in)[None, :]  # [1, n_in]
    overlap = np.clip(np.minimum(cells + 1, lo + s) - np.maximum(cells, lo), 0.0, None)
    return (overlap / s).astype(np.float32)


def _quantise(a: np.ndarray, bits: int) -> tuple[np.ndarray, object]:
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    if bits == 32:
        return np.ascontiguousarray(a, dtype=np.float32), oiio.FLOAT
    dtype, fmt, top = (np.uint8, oiio.UINT8, 255) if bits == 8 else (np.uint16, oiio.UINT16, 65535)
    if a.dtype == dtype:
        return np.ascontiguousarray(a), fmt
    if np.issubdtype(a.dtype, np.integer):
        raise ValueError(
            f"write_image: refusing to convert {a.dtype} pixels to {bits}-bit; pass floats in [0, 1]"
        )
    q = np.rint(np.clip(np.nan_to_num(a.astype(np.float32), nan=0.0), 0.0, 1.0) * top).astype(dtype)
    return np.ascontiguousarray(q), fmt


def _reorient(px: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation (2..8) with OIIO's ``ImageBufAlgo.reorient``.  # [H, W, C] -> [H', W', C]"""
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    h, w, c = px.shape
    buf = oiio.ImageBuf(oiio.ImageSpec(w, h, c, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(), np.ascontiguousarray(px))
    buf.specmod().attribute("Orientation", int(orientation))
    out = oiio.ImageBufAlgo.reorient(buf)
    if out.has_error:
        raise ValueError(f"EXIF reorientation failed: {out.geterror()}")
    s = out.spec()
    return np.asarray(out.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(s.height, s.width, s.nchannels)


def _first_line(msg: str | None) -> str:
    return (msg or "").strip().splitlines()[0] if (msg or "").strip() else ""


__all__ = [
    "DECODABLE_EXTENSIONS",
    "IMAGE_EXTENSIONS",
    "JPEG_EXTENSIONS",
    "ImageReadError",
    "image_orientation",
    "list_images",
    "read_image",
    "read_pixels",
    "resize_area",
    "resize_area_to",
    "write_image",
]
