"""The capture time of an image from its EXIF header (JPEG, TIFF, PNG), read without decoding the pixels.

The time is ``DateTimeOriginal`` plus ``SubSecTimeOriginal`` and ``OffsetTimeOriginal`` when present; without an
offset the EXIF time is read as UTC (cameras record local time without a zone). A file without a usable time (no
Exif block, no tag, a malformed or pre-1970 date, another format) has none: :func:`read_exif_time` returns None.
"""

from __future__ import annotations

import logging
import re
import struct
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import BinaryIO

log = logging.getLogger(__name__)

# Exif tags (CIPA DC-008): the Exif sub-IFD pointer in IFD0, and the capture-time tags inside it
TAG_EXIF_IFD, TAG_DATETIME_ORIGINAL, TAG_OFFSET_ORIGINAL, TAG_SUBSEC_ORIGINAL = 0x8769, 0x9003, 0x9011, 0x9291
MAX_HEADER_SEGMENTS = 64  # JPEG segments / PNG chunks looked at before giving up on finding Exif
MAX_IFD_ENTRIES = 1024
MAX_TIME_TAG_BYTES = 64  # a date is 20 bytes; anything much longer is not one


def read_exif_time(path: Path, opened: BinaryIO | None = None) -> float | None:
    """The EXIF capture time of a JPEG, TIFF or PNG file as Unix seconds, or None when it has no usable one.

    Reads only the header (the Exif block precedes the pixels; typically one 4 KiB read), never decodes. A small
    parser of its own rather than ``OpenImageIO.ImageInput.open(...).spec()``, which reads the same 4 KiB: on
    200 JPEGs of 2 MB it took 76-131 us per file (page cache) and 177-223 us (evicted) against OpenImageIO's
    120-202 us and 244-303 us (min-median of 11 rounds on a busy 2-core machine)."""
    try:
        with opened if opened is not None else open(path, "rb") as f:
            tags = _exif_time_tags(f)
    except (OSError, ValueError, struct.error) as e:
        log.debug("%s: unreadable Exif header (%s); using the file time", path, e)
        return None
    t = exif_timestamp(tags.get(TAG_DATETIME_ORIGINAL), tags.get(TAG_SUBSEC_ORIGINAL), tags.get(TAG_OFFSET_ORIGINAL))
    if t is None and tags.get(TAG_DATETIME_ORIGINAL):
        log.warning("%s: EXIF DateTimeOriginal %r is not a date; using the file time", path,
                    tags[TAG_DATETIME_ORIGINAL])
    return t


def _exif_time_tags(f: BinaryIO) -> dict[int, str]:
    """The capture-time tags of an open image file ({} when it has no Exif block)."""
    head = f.read(8)
    if head[:2] == b"\xff\xd8":
        base = _jpeg_exif_base(f)
    elif head[:4] in (b"II*\0", b"MM\0*"):
        base = 0
    elif head == b"\x89PNG\r\n\x1a\n":
        base = _png_exif_base(f)
    else:
        return {}
    return {} if base is None else _tiff_time_tags(f, base)


def _jpeg_exif_base(f: BinaryIO) -> int | None:
    """Offset of the TIFF header inside the JPEG's ``Exif`` APP1 segment; None when there is none before the scan."""
    pos = 2
    for _ in range(MAX_HEADER_SEGMENTS):
        f.seek(pos)
        seg = f.read(10)
        if len(seg) < 4 or seg[0] != 0xFF or seg[1] in (0xD9, 0xDA):  # end of image / start of scan
            return None
        if seg[1] == 0xE1 and seg[4:10] == b"Exif\0\0":
            return pos + 10
        pos += 2 + int.from_bytes(seg[2:4], "big")
    return None


def _png_exif_base(f: BinaryIO) -> int | None:
    """Offset of the PNG's ``eXIf`` chunk data (a TIFF header); None when there is none before the pixels."""
    pos = 8
    for _ in range(MAX_HEADER_SEGMENTS):
        f.seek(pos)
        chunk = f.read(8)
        if len(chunk) < 8 or chunk[4:] in (b"IDAT", b"IEND"):
            return None
        if chunk[4:] == b"eXIf":
            return pos + 8
        pos += 12 + int.from_bytes(chunk[:4], "big")
    return None


def _tiff_time_tags(f: BinaryIO, base: int) -> dict[int, str]:
    """DateTimeOriginal, SubSecTimeOriginal and OffsetTimeOriginal from the Exif IFD of the TIFF at ``base``."""
    f.seek(base)
    head = f.read(8)
    order = {b"II": "<", b"MM": ">"}.get(head[:2])
    if order is None or struct.unpack(order + "H", head[2:4])[0] != 42:
        return {}
    ifd0 = _read_ifd(f, base, order, struct.unpack(order + "I", head[4:8])[0])
    pointer = ifd0.get(TAG_EXIF_IFD)
    if pointer is None or pointer[0] not in (4, 13):  # LONG or IFD
        return {}
    exif = _read_ifd(f, base, order, struct.unpack(order + "I", pointer[2])[0])
    return {tag: _read_ascii(f, base, order, *exif[tag][1:]) for tag in
            (TAG_DATETIME_ORIGINAL, TAG_SUBSEC_ORIGINAL, TAG_OFFSET_ORIGINAL) if tag in exif and exif[tag][0] == 2}


def _read_ifd(f: BinaryIO, base: int, order: str, offset: int) -> dict[int, tuple[int, int, bytes]]:
    """One IFD: tag -> (type, count, the 4 value-or-offset bytes)."""
    f.seek(base + offset)
    (n,) = struct.unpack(order + "H", f.read(2))
    if n > MAX_IFD_ENTRIES:
        raise ValueError(f"implausible IFD with {n} entries")
    data = f.read(12 * n)
    out = {}
    for i in range(0, len(data) - 11, 12):
        tag, kind, count = struct.unpack(order + "HHI", data[i:i + 8])
        out[tag] = (kind, count, data[i + 8:i + 12])
    return out


def _read_ascii(f: BinaryIO, base: int, order: str, count: int, value: bytes) -> str:
    """An ASCII tag's text (up to its first NUL); '' for one too long to be a time."""
    if count > MAX_TIME_TAG_BYTES:
        return ""
    if count > 4:
        f.seek(base + struct.unpack(order + "I", value)[0])
        value = f.read(count)
    return value[:count].split(b"\0", 1)[0].decode("ascii", "replace")


_UTC_OFFSET = re.compile(r"([+-])(\d\d):(\d\d)")


def exif_timestamp(original: str | None, subsec: str | None, offset: str | None) -> float | None:
    """Unix seconds from EXIF ``YYYY:MM:DD HH:MM:SS``, fractional digits and ``±HH:MM`` (UTC without one);
    None for a missing, malformed or pre-1970 date."""
    try:
        dt = datetime.strptime((original or "").strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    if dt.year < 1970:
        return None
    tz = UTC
    m = _UTC_OFFSET.fullmatch((offset or "").strip())
    if m and int(m[2]) < 24 and int(m[3]) < 60:
        tz = timezone((-1 if m[1] == "-" else 1) * timedelta(hours=int(m[2]), minutes=int(m[3])))
    t = dt.replace(tzinfo=tz).timestamp()
    digits = (subsec or "").strip()
    return t + int(digits) / 10 ** len(digits) if digits.isdigit() else t
