"""What a survey recorded per frame: the altimeter's camera-to-bottom distance, the GPS position, the capture time.

Two sources, merged per image name: the photos' own EXIF (``SubjectDistance`` in the Exif IFD, as AIMS ReefScan
frames carry the altimeter; ``GPSLatitude``/``GPSLongitude`` in the GPS IFD; ``DateTimeOriginal``), and a telemetry
CSV (an ROV's or towed camera's log) whose rows name the frame's file. The CSV wins where both have a value: it
is the survey's own record, while EXIF may hold a camera's focus distance rather than an altimeter's.

CSV columns (case-insensitive; AIMS ``frames.csv`` uses the first of each): ``file`` | ``name`` | ``image``;
``camera_to_bottom_m`` | ``altitude_m`` | ``altitude``; ``lat`` | ``latitude``; ``lon`` | ``longitude``;
``datetime`` | ``time``. Rows are matched to images by file name, then by stem (ingest flattens sub-folders to
``a__b__name``: the last part is matched too).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, replace
from pathlib import Path

from PIL import Image

from pipeline.scene.exif_tags import (
    GPS_LAT,
    GPS_LAT_REF,
    GPS_LON,
    GPS_LON_REF,
    IFD_EXIF,
    IFD_GPS,
    TAG_DATETIME_ORIGINAL,
    TAG_SUBJECT_DISTANCE,
)

log = logging.getLogger(__name__)

COLUMNS: dict[str, tuple[str, ...]] = {
    "file": ("file", "name", "image", "filename"),
    "distance": ("camera_to_bottom_m", "altitude_m", "altitude", "subject_distance"),
    "lat": ("lat", "latitude"),
    "lon": ("lon", "longitude"),
    "time": ("datetime", "time", "timestamp"),
}


@dataclass(frozen=True)
class FrameRecord:
    """One frame's records; None where the survey did not record it."""

    distance_m: float | None = None  # camera-to-bottom distance (altimeter), metres
    lat: float | None = None  # degrees, WGS 84
    lon: float | None = None
    time: str | None = None  # as recorded ("YYYY:MM:DD HH:MM:SS")
    source: str = ""  # "exif", "telemetry" or "exif+telemetry"


def _deg(dms, ref) -> float | None:
    try:
        d, m, s = (float(x) for x in dms)
    except (TypeError, ValueError):
        return None
    value = d + m / 60 + s / 3600
    return -value if str(ref).upper() in ("S", "W") else value


def exif_record(path: Path) -> FrameRecord:
    """The records in one photo's EXIF (an empty record for a photo without them, or an unreadable one)."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub, gps = exif.get_ifd(IFD_EXIF), exif.get_ifd(IFD_GPS)
    except (OSError, ValueError, SyntaxError):
        return FrameRecord()
    dist = sub.get(TAG_SUBJECT_DISTANCE)
    try:
        dist = float(dist) if dist is not None else None
    except (TypeError, ValueError, ZeroDivisionError):
        dist = None
    if dist is not None and not 0 < dist < 1e4:  # 0 = unknown, 0xFFFFFFFF = infinity in EXIF's convention
        dist = None
    lat = _deg(gps.get(GPS_LAT), gps.get(GPS_LAT_REF)) if GPS_LAT in gps else None
    lon = _deg(gps.get(GPS_LON), gps.get(GPS_LON_REF)) if GPS_LON in gps else None
    time = sub.get(TAG_DATETIME_ORIGINAL)
    if dist is None and lat is None and time is None:
        return FrameRecord()
    return FrameRecord(dist, lat, lon, str(time) if time else None, "exif")


def _column(header: list[str], key: str) -> str | None:
    lower = {h.strip().lower(): h for h in header}
    return next((lower[c] for c in COLUMNS[key] if c in lower), None)


def _float(text: str | None) -> float | None:
    try:
        v = float(text) if text not in (None, "") else None
    except ValueError:
        return None
    return v if v is not None and v == v else None


def read_telemetry(path: Path) -> dict[str, FrameRecord]:
    """A telemetry CSV -> file name -> record. ValueError when it has no file column or nothing to use."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        header = reader.fieldnames or []
        cols = {k: _column(header, k) for k in COLUMNS}
        if cols["file"] is None:
            raise ValueError(f"{path.name}: no file-name column (one of {', '.join(COLUMNS['file'])})")
        if cols["distance"] is None and cols["lat"] is None:
            raise ValueError(f"{path.name}: neither a camera-to-bottom column ({', '.join(COLUMNS['distance'])}) "
                             f"nor a position ({', '.join(COLUMNS['lat'])})")
        out = {}
        for row in reader:
            name = (row.get(cols["file"]) or "").strip()
            if not name:
                continue
            get = {k: (row.get(c) if c else None) for k, c in cols.items()}
            out[Path(name).name] = FrameRecord(_float(get["distance"]), _float(get["lat"]), _float(get["lon"]),
                                               get["time"] or None, "telemetry")
    return out


def _match(name: str, table: dict[str, FrameRecord]) -> FrameRecord | None:
    """The telemetry row of image ``name`` (ingest's flattened ``a__b__x.jpg`` matches ``x.jpg``; a converted
    ``x.png`` matches ``x.jpg`` by stem)."""
    for candidate in (name, name.split("__")[-1]):
        if candidate in table:
            return table[candidate]
    stem = Path(name.split("__")[-1]).stem
    return next((r for n, r in table.items() if Path(n).stem == stem), None)


def merge(exif: FrameRecord, telemetry: FrameRecord | None) -> FrameRecord:
    """The telemetry's values where it has them, EXIF's elsewhere."""
    if telemetry is None:
        return exif
    both = exif.source != ""
    return replace(exif, **{k: v for k, v in vars(telemetry).items() if v is not None and k != "source"},
                   source="exif+telemetry" if both else "telemetry")


def frame_records(images: dict[str, Path], telemetry: Path | None = None) -> dict[str, FrameRecord]:
    """Image name -> its records, from each photo's EXIF and the telemetry CSV when given."""
    table = read_telemetry(telemetry) if telemetry is not None else {}
    out = {name: merge(exif_record(path), _match(name, table) if table else None) for name, path in images.items()}
    if table:
        matched = sum(r.source != "exif" and r.source != "" for r in out.values())
        log.info("telemetry %s: %d rows, %d of %d images matched", telemetry, len(table), matched, len(images))
    return out


__all__ = ["FrameRecord", "exif_record", "frame_records", "merge", "read_telemetry"]
