"""The survey's frame: the plane the seabed lies in, metres, and where on Earth (a UTM zone) when GPS says so.

A model from SfM has an arbitrary origin, orientation and unit. The products need a map frame: x and y in the
survey plane (the robust plane through the sparse points, its normal pointing to the cameras: "up"), heights
along the normal, metres when the scale is known. With GPS on the frames, the plane's axes are turned (and
shifted) to east and north in the survey's UTM zone by fitting the camera centres to the GPS track; a towed
camera's GPS sits on the boat, so a poor fit (residual large against the track) is reported and the local frame
kept. Heights stay above the fitted plane: SfM does not know gravity, and a survey plane is what a reef's
elevation model is read against.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pyproj

from pipeline.survey.records import FrameRecord

log = logging.getLogger(__name__)

# A GPS fit is poor when its RMS residual exceeds this many metres and this share of the track's extent.
GPS_MAX_RESIDUAL_M = 1.5
GPS_MAX_RESIDUAL_SHARE = 0.25
GPS_MIN_FRAMES = 3
HEADING_WARN_DEG = 10.0  # an orientation less certain than this is said in the note and the warnings
GPS_MIN_EXTENT_M = 2.0  # a track shorter than this does not fix the rotation against GPS noise (a few metres)


@dataclass(frozen=True)
class SurveyFrame:
    """World (scene units) -> map coordinates: ``[x, y, h] = scale · Q (p − origin) + [east0, north0, 0]``.

    Q's rows are the plane's two axes and its up normal (a proper rotation); x, y are the map's east and north
    (or the plane's axes in a local frame), h the height above the survey plane."""

    origin: np.ndarray  # [3] world point on the plane
    Q: np.ndarray  # [3, 3]
    scale: float  # map units (metres, or scene units without a metric scale) per scene unit
    offset: np.ndarray  # [2] map coordinates of the origin (UTM easting, northing; 0, 0 locally)
    epsg: int | None = None  # the map's CRS; None: a local frame
    crs_name: str = "local metric frame (not georeferenced)"

    def to_map(self, p: np.ndarray) -> np.ndarray:
        """World points [..., 3] -> map coordinates [..., 3]."""
        m = self.scale * (np.asarray(p, np.float64) - self.origin) @ self.Q.T
        m[..., :2] += self.offset
        return m

    def to_world(self, m: np.ndarray) -> np.ndarray:
        """Map coordinates [..., 3] -> world points [..., 3]."""
        m = np.array(m, np.float64, copy=True)
        m[..., :2] -= self.offset
        return (m / self.scale) @ self.Q + self.origin


def fit_plane(points: np.ndarray, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Robust plane through ``points`` [N, 3]: (a point on it, unit normal). Least squares (SVD), then points
    beyond 3 robust standard deviations are dropped and the plane refitted (``rounds`` times): SfM's stray
    points do not tilt it."""
    p = np.asarray(points, np.float64)
    if len(p) < 3:
        raise ValueError(f"a plane needs >= 3 points, got {len(p)}")
    keep = np.ones(len(p), bool)
    for _ in range(rounds):
        c = p[keep].mean(0)
        normal = np.linalg.svd(p[keep] - c, full_matrices=False)[2][2]
        d = (p - c) @ normal
        mad = np.median(np.abs(d[keep] - np.median(d[keep]))) * 1.4826
        new = np.abs(d - np.median(d[keep])) <= 3 * max(mad, 1e-12)
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    c = p[keep].mean(0)
    return c, np.linalg.svd(p[keep] - c, full_matrices=False)[2][2]


def plane_frame(points: np.ndarray, centres: np.ndarray, scale: float, units: str = "m") -> SurveyFrame:
    """The local frame of the survey plane: up towards the cameras, x along the plane's longer extent of the
    sparse points (a survey line runs along x)."""
    origin, n = fit_plane(points)
    if np.median((np.asarray(centres) - origin) @ n) < 0:
        n = -n
    flat = (points - origin) - np.outer((points - origin) @ n, n)
    e1 = np.linalg.svd(flat - flat.mean(0), full_matrices=False)[2][0]
    e1 = e1 - (e1 @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)  # right-handed: x, y on the plane, h up
    name = ("local metric frame (not georeferenced)" if units == "m"
            else "local frame, arbitrary units (no metric scale)")
    return SurveyFrame(origin, np.stack([e1, e2, n]), scale, np.zeros(2), None, name)


def utm_epsg(lat: float, lon: float) -> int:
    """The EPSG code of the WGS 84 / UTM zone holding (lat, lon): 326zz north, 327zz south."""
    zone = int((lon + 180) // 6) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


def _procrustes_2d(src: np.ndarray, dst: np.ndarray, scale: float | None) -> tuple[float, np.ndarray, np.ndarray]:
    """``dst ≈ s R src + t`` in 2D (R a proper rotation); ``scale`` fixed when given, else fitted."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    cov = b.T @ a
    U, D, Vt = np.linalg.svd(cov)
    S = np.diag([1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / max((a**2).sum(), 1e-18)) if scale is None else scale
    return s, R, md - s * R @ ms


@dataclass(frozen=True)
class GpsFit:
    frame: SurveyFrame  # georeferenced, or the local frame when the fit is poor
    georeferenced: bool
    residual_m: float | None  # RMS of camera centres against the GPS track after the fit
    extent_m: float | None  # the GPS track's largest extent
    scale: float | None  # metres per scene unit the fit implies (used when nothing better measured it)
    frames: int
    note: str
    heading_sigma_deg: float | None = None  # the map's orientation's uncertainty (a line fit's: σ·√(12/N) / L)


def heading_sigma_deg(cam_m: np.ndarray, residual_m: float) -> float:
    """One-σ uncertainty of the fitted orientation, degrees: a line of N camera centres L metres long, each off its
    GPS position by ``residual_m`` (RMS), fixes its direction to σ·√(12/N) / L radians."""
    c = cam_m - cam_m.mean(0)
    length = 2 * np.sqrt(3) * float(np.sqrt(np.linalg.eigvalsh(c.T @ c / len(c))[-1]))  # a uniform line's length
    return float(np.degrees(np.arctan(residual_m * np.sqrt(12 / len(c)) / max(length, 1e-9))))


def georeference(local: SurveyFrame, centres: dict[str, np.ndarray], records: dict[str, FrameRecord],
                 scale_known: bool) -> GpsFit:
    """Turn the local plane frame to east/north in the survey's UTM zone by fitting camera centres to the GPS
    track (rotation and shift; the scale too when ``scale_known`` is False). Returns the local frame with the
    reason when there is too little GPS or the fit is poor."""
    names = [n for n in centres if records.get(n) and records[n].lat is not None and records[n].lon is not None]
    if len(names) < GPS_MIN_FRAMES:
        note = "no GPS on the frames" if not names else f"GPS on only {len(names)} frames"
        return GpsFit(local, False, None, None, None, len(names), note)
    lat = np.array([records[n].lat for n in names])
    lon = np.array([records[n].lon for n in names])
    epsg = utm_epsg(float(np.median(lat)), float(np.median(lon)))
    to_utm = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    east, north = to_utm.transform(lon, lat)
    gps = np.stack([east, north], 1)
    extent = float(np.ptp(gps, axis=0).max())
    cam = local.to_map(np.stack([centres[n] for n in names]))[:, :2]
    if extent < GPS_MIN_EXTENT_M:
        return GpsFit(local, False, None, extent, None, len(names),
                      f"the GPS track spans {extent:.1f} m: too short to fix the map's orientation")
    s, R, t = _procrustes_2d(cam, gps, 1.0 if scale_known else None)
    resid = float(np.sqrt(((s * cam @ R.T + t - gps) ** 2).sum(1).mean()))
    crs_name = pyproj.CRS.from_epsg(epsg).name
    if resid > max(GPS_MAX_RESIDUAL_M, GPS_MAX_RESIDUAL_SHARE * extent):
        return GpsFit(local, False, resid, extent, None, len(names),
                      f"the camera track does not fit the GPS track (RMS {resid:.2f} m over {extent:.1f} m): a "
                      f"towed camera's GPS on the boat? The products stay in the local frame")
    R3 = np.eye(3)
    R3[:2, :2] = R
    frame = SurveyFrame(local.origin, R3 @ local.Q, local.scale * s, t, epsg, crs_name)
    sigma = heading_sigma_deg(s * cam, resid)
    note = (f"camera centres fitted to the GPS track of {len(names)} frames: RMS {resid:.2f} m over {extent:.1f} m; "
            f"orientation ±{sigma:.0f}°")
    if sigma > HEADING_WARN_DEG:
        note += (f" (the camera track is short against the GPS's scatter: north on the map may be off by that much; "
                 f"the position is good to about {resid:.1f} m)")
    log.info("georeference: %s (%s)", note, crs_name)
    return GpsFit(frame, True, resid, extent, None if scale_known else local.scale * s, len(names), note, sigma)


__all__ = ["GpsFit", "SurveyFrame", "fit_plane", "georeference", "plane_frame", "utm_epsg"]
