"""Banded image reading and writing with the source's metadata kept (OpenImageIO).

A 27 MP frame never sits in memory whole: :class:`BandReader` reads scanline ranges in order and keeps only the
rows the current band and its halo need; :class:`BandWriter` writes scanlines in order. The restored image keeps
the source's metadata (EXIF, ICC, ...) and its format: JPEG in → JPEG out at quality 95 without chroma
subsampling, PNG in → PNG out, anything else (or ``tiff16``) → 16-bit TIFF.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from pipeline.scene.images import PNG_COMPRESSION_LEVEL

JPEG_QUALITY = 95
# attributes that describe the source's encoding, not the picture: never copied
_DROP = ("oiio:BitsPerSample", "oiio:UnassociatedAlpha", "Compression", "CompressionQuality", "oiio:Gamma",
         "PixelAspectRatio", "png:compressionLevel")


class BandReader:
    """Rows of an image file in order, as stored (uint8 or uint16, first 3 channels).

    Raises ValueError for a file whose EXIF Orientation is not 1: its stored rows are not the display
    orientation the cameras were calibrated in (ingest rotates such files; restore the ingested copy)."""

    def __init__(self, path: Path):
        self.inp = oiio.ImageInput.open(str(path))
        if self.inp is None:
            raise OSError(f"cannot open {path}: {oiio.geterror()}")
        self.spec = self.inp.spec()
        if self.spec.get_int_attribute("Orientation", 1) != 1:
            raise ValueError(f"{path}: EXIF Orientation {self.spec.get_int_attribute('Orientation', 1)} != 1")
        if self.spec.nchannels < 3:
            raise ValueError(f"{path}: {self.spec.nchannels} channels, need RGB")
        self.width, self.height = self.spec.width, self.spec.height
        self.dtype = np.uint16 if self.spec.format.basetype in (oiio.UINT16, oiio.FLOAT, oiio.HALF) else np.uint8
        self._buf = np.zeros((0, self.width, 3), self.dtype)
        self._y0 = 0  # file row of _buf[0]

    def rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows [y0, y1) [y1−y0, W, 3]; y0 never below an earlier call's y0, y1 never above H."""
        if y0 < self._y0:
            raise ValueError("BandReader reads forwards only")
        have = self._y0 + len(self._buf)
        keep = self._buf[max(0, y0 - self._y0):]
        if y1 > have:
            fmt = oiio.UINT16 if self.dtype == np.uint16 else oiio.UINT8
            new = self.inp.read_scanlines(0, 0, max(have, y0), y1, 0, 0, 3, fmt)
            if new is None:
                raise OSError(f"read_scanlines failed: {self.inp.geterror()}")
            keep = np.concatenate([keep, new.reshape(-1, self.width, 3)])
        self._buf, self._y0 = keep, max(y0, self._y0)
        return self._buf[: y1 - y0]

    def close(self) -> None:
        self.inp.close()


def output_spec(src: oiio.ImageSpec | None, width: int, height: int, nchannels: int, fmt, path: Path,
                keep_metadata: bool = True) -> oiio.ImageSpec:
    """The spec of an output file: size, channels and pixel format given; the source's metadata copied."""
    spec = oiio.ImageSpec(width, height, nchannels, fmt)
    if src is not None and keep_metadata:
        for a in src.extra_attribs:
            encoding = a.name in _DROP or a.name.startswith(("tiff:", "png:", "jpeg:"))
            if not encoding:
                spec.attribute(a.name, a.type, a.value)
    if Path(path).suffix.lower() in (".jpg", ".jpeg"):
        spec.attribute("Compression", f"jpeg:{JPEG_QUALITY}")
        spec.attribute("jpeg:subsampling", "4:4:4")  # restored detail is amplified noise too: no chroma halving
    elif Path(path).suffix.lower() == ".png":
        spec.attribute("png:compressionLevel", PNG_COMPRESSION_LEVEL)
    spec.attribute("Orientation", 1)
    return spec


def restored_path(src: Path, out_dir: Path, tiff16: bool = False) -> Path:
    """Where the restored image of ``src`` goes: same name and format (JPEG, PNG), else or with ``tiff16`` a
    .tif."""
    suffix = src.suffix.lower()
    if tiff16 or suffix not in (".jpg", ".jpeg", ".png"):
        return out_dir / (src.stem + ".tif")
    return out_dir / src.name


class BandWriter:
    """Writes rows of one image in order."""

    def __init__(self, path: Path, spec: oiio.ImageSpec):
        self.path = Path(path)
        self.out = oiio.ImageOutput.create(str(path))
        if self.out is None or not self.out.open(str(path), spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        self.y = 0

    def write(self, rows: np.ndarray) -> None:
        """Append rows [n, W, C] (or [n, W]: one channel; OIIO misreads a 2-D array, so it gets its channel axis)."""
        n = rows.shape[0]
        rows = rows[..., None] if rows.ndim == 2 else rows
        if not self.out.write_scanlines(self.y, self.y + n, 0, np.ascontiguousarray(rows)):
            raise OSError(f"write failed for {self.path}: {self.out.geterror()}")
        self.y += n

    def close(self) -> None:
        self.out.close()
