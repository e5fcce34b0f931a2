"""The survey's own records of a generated photo-family scene: altimeter range, capture time and GPS per frame.

What a real survey camera records beside each photo (AIMS ReefScan: shared/data/real/aims-erub-mt81/frames.csv),
generated from the truth:

- camera-to-bottom distance (EXIF ``SubjectDistance``): the true distance from the camera centre to the seabed
  along the optical axis (the camera-space depth z at the principal point, one ray marched through the
  heightfield) times (1 + ε), ε ~ N(0, altimeter_noise²) per frame from its own seeded stream;
- capture time: ``capture_start`` (UTC) + i · ``capture_interval`` for frame i;
- latitude/longitude of the camera centre (world x east, y north through the UTM zone of ``gps_origin``:
  :mod:`.geo`), when the scene has a GPS origin.

:func:`write_survey_records` writes ``records.csv`` in the scene folder (columns of frames.csv plus the true
distance) and the same records into each photo's EXIF (:mod:`.exif_records`: images/ and pinhole/images/),
pixels untouched. The camera effects (:mod:`.defocus`, :mod:`.exposure`) rewrite images/ and drop the EXIF:
:func:`stamp_scene` writes it again from records.csv (``dualphys synth`` does so after them).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import torch

from pipeline.scene.records import View
from pipeline.synth.exif_records import ExifRecord, write_exif
from pipeline.synth.geo import WorldGeo
from pipeline.synth.photo_world import Terrain, march
from pipeline.synth.procedural import PINHOLE_DIR

log = logging.getLogger(__name__)

RECORDS_FILE = "records.csv"
COLUMNS = ("file", "datetime", "camera_to_bottom_m", "true_camera_to_bottom_m", "lat", "lon")
TIME_FORMAT = "%Y:%m:%d %H:%M:%S"  # frames.csv's; records.csv appends ".mmm" (frames 0.3 s apart share seconds)
DISTANCE_DECIMALS = 6  # metres (µm), as the EXIF rational holds them
DEGREE_DECIMALS = 10  # degrees (≈ 0.01 mm)


@dataclass(frozen=True)
class FrameRecord:
    """One frame's survey records (one row of records.csv)."""

    file: str  # the image's file name in images/
    time: datetime  # capture time, UTC, whole milliseconds
    camera_to_bottom_m: float | None  # the altimeter's reading (noisy); None = the camera has no altimeter
    true_camera_to_bottom_m: float  # the true distance along the optical axis
    lat: float | None  # camera centre latitude, degrees; None = no GPS
    lon: float | None  # camera centre longitude, degrees

    def exif(self) -> ExifRecord:
        return ExifRecord(self.time, self.camera_to_bottom_m, self.lat, self.lon)


def optical_axis_range(terrain: Terrain, views: list[View]) -> np.ndarray:
    """Distance from each camera centre to the heightfield along its optical axis (= camera z there).  # [V]"""
    if not views:
        return np.zeros(0)
    o = torch.as_tensor(np.stack([v.center for v in views]), dtype=torch.float64)  # [V, 3]
    d = torch.as_tensor(np.stack([v.R[2] for v in views]), dtype=torch.float64)  # camera +z in world: R^T e_z
    t = march(terrain, o, d).numpy()
    if not np.all(np.isfinite(t)):
        raise ValueError("a camera's optical axis does not point down at the seabed")
    return t


def parse_start(text: str) -> datetime:
    """ISO 8601 capture start; a time without a zone is UTC."""
    t = datetime.fromisoformat(text)
    return t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)


def frame_records(views: list[View], terrain: Terrain, *, altimeter_noise: float | None, rng: np.random.Generator,
                  start: datetime, interval: float, geo: WorldGeo | None) -> list[FrameRecord]:
    """Each view's records (module docstring). ``altimeter_noise``: relative std of the altimeter's error (0 =
    exact; None or negative = no altimeter); ``rng`` draws one error per view; ``geo``: None = no GPS."""
    true = optical_axis_range(terrain, views)
    has_altimeter = altimeter_noise is not None and altimeter_noise >= 0
    eps = rng.standard_normal(len(views)) * (altimeter_noise if has_altimeter else 0.0)
    if geo is not None and views:
        lat, lon = geo.latlon([v.center[0] for v in views], [v.center[1] for v in views])
    out = []
    for i, v in enumerate(views):
        t = start + timedelta(milliseconds=round(i * interval * 1000))
        measured = round(float(true[i] * (1 + eps[i])), DISTANCE_DECIMALS) if has_altimeter else None
        out.append(FrameRecord(v.name, t, measured, round(float(true[i]), DISTANCE_DECIMALS),
                               round(float(lat[i]), DEGREE_DECIMALS) if geo is not None else None,
                               round(float(lon[i]), DEGREE_DECIMALS) if geo is not None else None))
    return out


def _fmt(v: float | None, decimals: int) -> str:
    return "" if v is None else f"{v:.{decimals}f}"


def write_records_csv(root: Path, records: list[FrameRecord]) -> Path:
    """``root/records.csv``: one row per frame; empty cells where the camera recorded nothing."""
    path = Path(root) / RECORDS_FILE
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in records:
            w.writerow([r.file, r.time.strftime(TIME_FORMAT) + f".{r.time.microsecond // 1000:03d}",
                        _fmt(r.camera_to_bottom_m, DISTANCE_DECIMALS),
                        _fmt(r.true_camera_to_bottom_m, DISTANCE_DECIMALS),
                        _fmt(r.lat, DEGREE_DECIMALS), _fmt(r.lon, DEGREE_DECIMALS)])
    return path


def read_records_csv(root: str | Path) -> list[FrameRecord]:
    """The records :func:`write_records_csv` wrote in ``root``."""
    def num(s: str) -> float | None:
        return float(s) if s.strip() else None

    with (Path(root) / RECORDS_FILE).open(newline="") as f:
        return [FrameRecord(row["file"], datetime.strptime(row["datetime"], TIME_FORMAT + ".%f").replace(tzinfo=UTC),
                            num(row["camera_to_bottom_m"]), float(row["true_camera_to_bottom_m"]), num(row["lat"]),
                            num(row["lon"]))
                for row in csv.DictReader(f)]


def stamp_scene(root: str | Path, records: list[FrameRecord] | None = None) -> int:
    """Write each frame's records (default: root/records.csv) into the EXIF of images/<file> and, when there,
    pinhole/images/<file>. Returns the number of files stamped."""
    root = Path(root)
    records = read_records_csv(root) if records is None else records
    n = 0
    for folder in (root / "images", root / PINHOLE_DIR / "images"):
        if not folder.is_dir():
            continue
        for r in records:
            write_exif(folder / r.file, r.exif())
            n += 1
    log.debug("stamped survey records into %d photos of %s", n, root)
    return n


def write_survey_records(root: str | Path, records: list[FrameRecord]) -> None:
    """records.csv and the photos' EXIF of the scene in ``root``."""
    write_records_csv(Path(root), records)
    stamp_scene(root, records)


__all__ = ["COLUMNS", "FrameRecord", "RECORDS_FILE", "frame_records", "optical_axis_range", "parse_start",
           "read_records_csv", "stamp_scene", "write_records_csv", "write_survey_records"]
