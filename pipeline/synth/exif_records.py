"""A survey frame's records in its image file's EXIF, laid out as a real survey camera writes them.

The layout follows the AIMS ReefScan frames (shared/data/real/aims-erub-mt81) in standard EXIF (CIPA DC-008 2.32):

- IFD0: ``DateTime`` (0x0132), pointers to the Exif IFD (0x8769) and the GPS IFD (0x8825);
- Exif IFD: ``DateTimeOriginal`` (0x9003) and ``DateTimeDigitized`` (0x9004) "YYYY:MM:DD HH:MM:SS",
  ``SubSecTimeOriginal`` (0x9291) milliseconds as three digits, ``OffsetTimeOriginal`` (0x9011) "+00:00" (the
  times are UTC), ``SubjectDistance`` (0x9206, RATIONAL, metres: the altimeter's camera-to-bottom distance);
- GPS IFD (only with a position): ``GPSVersionID`` 2.2.0.0, ``GPSLatitudeRef`` "N"/"S", ``GPSLatitude`` and
  ``GPSLongitudeRef`` "E"/"W", ``GPSLongitude`` as (degrees, minutes, seconds) RATIONALs (seconds to 1e-6″, about
  0.03 mm), ``GPSDateStamp`` "YYYY:MM:DD" and ``GPSTimeStamp`` (h, m, s) UTC. No ``GPSAltitude``: ReefScan writes
  the water depth there (not the standard altitude), and a generated world has no water surface.

The block is built with Pillow (``Image.Exif``) and spliced into the file without re-encoding it: a PNG's
``eXIf`` chunk (replacing one already there, else placed after ``IHDR``), a JPEG's ``Exif`` APP1 segment (likewise,
else placed after SOI). The pixel bytes are untouched. :func:`read_records` reads the records back (Pillow).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from pipeline.scene.exif_tags import (
    GPS_ALT,
    GPS_ALT_REF,
    GPS_DATE,
    GPS_LAT,
    GPS_LAT_REF,
    GPS_LON,
    GPS_LON_REF,
    GPS_TIME,
    GPS_VERSION,
    IFD_EXIF,
    IFD_GPS,
    TAG_DATETIME,
    TAG_DATETIME_DIGITIZED,
    TAG_DATETIME_ORIGINAL,
    TAG_OFFSET_TIME_ORIGINAL,
    TAG_SUBJECT_DISTANCE,
    TAG_SUBSEC_TIME_ORIGINAL,
)

DISTANCE_DENOMINATOR = 1_000_000  # SubjectDistance in micrometres (fits 32 bits up to 4 km)
ARCSEC_DENOMINATOR = 1_000_000  # GPS seconds of arc to 1e-6″ (≈ 0.03 mm on the ground)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8"


@dataclass(frozen=True)
class ExifRecord:
    """What one frame's EXIF carries."""

    time: datetime  # capture time, timezone-aware (written as UTC)
    subject_distance_m: float | None  # the altimeter's camera-to-bottom distance; None = no tag
    lat: float | None  # degrees, WGS 84; None = no GPS IFD (lat and lon go together)
    lon: float | None  # degrees, WGS 84


def _dms(deg: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    """|deg| as (degrees, minutes, seconds) rationals, seconds to 1/ARCSEC_DENOMINATOR″."""
    total = round(abs(deg) * 3600 * ARCSEC_DENOMINATOR)  # integer micro-arcseconds: no float carry errors
    d, rest = divmod(total, 3600 * ARCSEC_DENOMINATOR)
    m, s = divmod(rest, 60 * ARCSEC_DENOMINATOR)
    return IFDRational(d, 1), IFDRational(m, 1), IFDRational(s, ARCSEC_DENOMINATOR)


def exif_bytes(rec: ExifRecord) -> bytes:
    """The TIFF-structured EXIF block of ``rec`` (starting at the byte-order mark, no "Exif\\0\\0" prefix)."""
    t = rec.time.astimezone(UTC)
    stamp = t.strftime("%Y:%m:%d %H:%M:%S")
    exif = Image.Exif()
    exif[TAG_DATETIME] = stamp
    sub = exif.get_ifd(IFD_EXIF)
    sub[TAG_DATETIME_ORIGINAL] = stamp
    sub[TAG_DATETIME_DIGITIZED] = stamp
    sub[TAG_SUBSEC_TIME_ORIGINAL] = f"{t.microsecond // 1000:03d}"
    sub[TAG_OFFSET_TIME_ORIGINAL] = "+00:00"
    if rec.subject_distance_m is not None:
        if not rec.subject_distance_m >= 0:
            raise ValueError(f"subject distance must be >= 0 m, got {rec.subject_distance_m}")
        sub[TAG_SUBJECT_DISTANCE] = IFDRational(round(rec.subject_distance_m * DISTANCE_DENOMINATOR),
                                                DISTANCE_DENOMINATOR)
    if (rec.lat is None) != (rec.lon is None):
        raise ValueError("latitude and longitude go together")
    if rec.lat is not None and rec.lon is not None:
        gps = exif.get_ifd(IFD_GPS)
        gps[GPS_VERSION] = b"\x02\x02\x00\x00"
        gps[GPS_LAT_REF] = "N" if rec.lat >= 0 else "S"
        gps[GPS_LAT] = _dms(rec.lat)
        gps[GPS_LON_REF] = "E" if rec.lon >= 0 else "W"
        gps[GPS_LON] = _dms(rec.lon)
        gps[GPS_TIME] = (IFDRational(t.hour, 1), IFDRational(t.minute, 1),
                         IFDRational(t.second * 1000 + t.microsecond // 1000, 1000))
        gps[GPS_DATE] = t.strftime("%Y:%m:%d")
    block = exif.tobytes()
    return block[6:] if block.startswith(b"Exif\x00\x00") else block


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")


def _splice_png(png: bytes, block: bytes) -> bytes:
    """``png`` with its eXIf chunk replaced by ``block`` (or one inserted after IHDR)."""
    chunks, pos = [], len(PNG_SIGNATURE)
    while pos < len(png):
        n = int.from_bytes(png[pos:pos + 4], "big")
        chunks.append((png[pos + 4:pos + 8], png[pos:pos + 12 + n]))
        pos += 12 + n
    if not chunks or chunks[0][0] != b"IHDR":
        raise ValueError("not a PNG stream: the first chunk is not IHDR")
    new = _png_chunk(b"eXIf", block)
    kinds = [k for k, _ in chunks]
    at = kinds.index(b"eXIf") if b"eXIf" in kinds else 1
    out = [raw for k, raw in chunks if k != b"eXIf"]
    out.insert(at, new)
    return PNG_SIGNATURE + b"".join(out)


def _splice_jpeg(jpg: bytes, block: bytes) -> bytes:
    """``jpg`` with its Exif APP1 segment replaced by ``block`` (or one inserted after SOI)."""
    payload = b"Exif\x00\x00" + block
    if len(payload) + 2 > 0xFFFF:
        raise ValueError(f"EXIF block too large for a JPEG segment ({len(payload)} bytes)")
    segment = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    pos = 2
    while pos + 4 <= len(jpg) and jpg[pos] == 0xFF and jpg[pos + 1] not in (0xD9, 0xDA):  # up to the scan
        end = pos + 2 + int.from_bytes(jpg[pos + 2:pos + 4], "big")
        if jpg[pos + 1] == 0xE1 and jpg[pos + 4:pos + 10] == b"Exif\x00\x00":
            return jpg[:pos] + segment + jpg[end:]
        pos = end
    return JPEG_SOI + segment + jpg[2:]


def write_exif(path: str | Path, rec: ExifRecord) -> None:
    """Put ``rec`` into the PNG or JPEG file ``path`` (by content), replacing any EXIF it holds; pixels untouched."""
    path = Path(path)
    data = path.read_bytes()
    block = exif_bytes(rec)
    if data.startswith(PNG_SIGNATURE):
        out = _splice_png(data, block)
    elif data.startswith(JPEG_SOI):
        out = _splice_jpeg(data, block)
    else:
        raise ValueError(f"{path}: only PNG and JPEG files take EXIF records here")
    tmp = path.with_name(path.name + ".exif-tmp")
    tmp.write_bytes(out)
    tmp.replace(path)  # a reader never sees half a file


def _rational(v) -> float:
    return float(v.numerator) / float(v.denominator) if hasattr(v, "denominator") else float(v)


def read_records(path: str | Path) -> dict:
    """The survey records in an image's EXIF (Pillow): {"time": aware datetime or None, "subject_distance_m",
    "lat", "lon", "gps_altitude_m": floats or None}. Latitude/longitude are signed by their refs; the time takes
    SubSecTimeOriginal and OffsetTimeOriginal (UTC without one)."""
    with Image.open(path) as im:
        exif = im.getexif()
    sub, gps = exif.get_ifd(IFD_EXIF), exif.get_ifd(IFD_GPS)
    time = None
    if TAG_DATETIME_ORIGINAL in sub:
        time = datetime.strptime(str(sub[TAG_DATETIME_ORIGINAL]).strip(), "%Y:%m:%d %H:%M:%S")
        digits = str(sub.get(TAG_SUBSEC_TIME_ORIGINAL, "")).strip()
        offset = str(sub.get(TAG_OFFSET_TIME_ORIGINAL, "+00:00")).strip()
        time = datetime.fromisoformat(time.isoformat() + (f".{digits}" if digits.isdigit() else "") + offset)

    def angle(tag: int, ref: int, negative: str) -> float | None:
        if tag not in gps:
            return None
        d, m, s = (_rational(v) for v in gps[tag])
        return (-1.0 if str(gps.get(ref, "")).strip().upper() == negative else 1.0) * (d + m / 60 + s / 3600)

    alt = None
    if GPS_ALT in gps:
        alt = _rational(gps[GPS_ALT]) * (-1.0 if gps.get(GPS_ALT_REF) in (1, b"\x01") else 1.0)
    distance = _rational(sub[TAG_SUBJECT_DISTANCE]) if TAG_SUBJECT_DISTANCE in sub else None
    return {"time": time, "subject_distance_m": distance, "lat": angle(GPS_LAT, GPS_LAT_REF, "S"),
            "lon": angle(GPS_LON, GPS_LON_REF, "W"), "gps_altitude_m": alt}


__all__ = ["ExifRecord", "exif_bytes", "read_records", "write_exif"]
