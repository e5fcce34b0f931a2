"""A generated scene's world placed on the Earth: world x, y (metres) ↔ WGS 84 latitude/longitude.

World frame of the generated scenes: metres, z up, **x east, y north**. With a GPS origin (lat, lon of the world
origin, degrees) a world point (x, y) sits at UTM easting E0 + x, northing N0 + y, where (E0, N0) is the origin's
position in the UTM zone of the origin (WGS 84, EPSG 326zz north of the equator / 327zz south; the standard
6° zones, without the Norway/Svalbard exceptions). So world metres are UTM grid metres: true ground distances
differ by the UTM point scale factor (0.9996 on the central meridian, up to about 1.0010 at a zone's edge) and
world y points to grid north (within a few degrees of true north, the grid convergence). A reader that converts
the latitude/longitude back through the same zone (:attr:`WorldGeo.crs`) recovers world x, y exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import CRS, Transformer

WGS84 = "EPSG:4326"


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS 84 UTM zone holding (lat, lon) in degrees (standard 6° zones)."""
    if not -80.0 <= lat <= 84.0 or not -180.0 <= lon <= 180.0:
        raise ValueError(f"UTM covers latitudes -80..84 and longitudes -180..180, got ({lat}, {lon})")
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


@dataclass
class WorldGeo:
    """The world origin at ``origin`` (lat, lon degrees); conversions through the origin's UTM zone."""

    origin: tuple[float, float]  # (latitude, longitude) of world (0, 0), degrees
    epsg: int = field(init=False)  # the UTM zone's EPSG code
    origin_en: tuple[float, float] = field(init=False)  # the origin's UTM (easting, northing), metres

    def __post_init__(self) -> None:
        lat, lon = (float(v) for v in self.origin)
        self.origin = (lat, lon)
        self.epsg = utm_epsg(lat, lon)
        self._to_utm = Transformer.from_crs(WGS84, CRS.from_epsg(self.epsg), always_xy=True)
        self._to_geo = Transformer.from_crs(CRS.from_epsg(self.epsg), WGS84, always_xy=True)
        e, n = self._to_utm.transform(lon, lat)
        self.origin_en = (float(e), float(n))

    @property
    def crs(self) -> str:
        """The projected CRS whose metres are world metres (shifted by :attr:`origin_en`), e.g. "EPSG:32755"."""
        return f"EPSG:{self.epsg}"

    def latlon(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """World x (east), y (north) in metres, any equal shapes → (latitude, longitude) in degrees."""
        e, n = np.asarray(x, dtype=np.float64) + self.origin_en[0], np.asarray(y, dtype=np.float64) + self.origin_en[1]
        lon, lat = self._to_geo.transform(e, n)
        return np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)

    def world_xy(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """(latitude, longitude) in degrees, any equal shapes → world (x, y) in metres."""
        e, n = self._to_utm.transform(np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64))
        return np.asarray(e, dtype=np.float64) - self.origin_en[0], np.asarray(n, dtype=np.float64) - self.origin_en[1]

    def to_json(self) -> dict:
        """What water.json records of the placement."""
        return {"origin_lat_lon": list(self.origin), "crs": self.crs, "origin_easting_northing_m": list(self.origin_en),
                "convention": "world x = UTM easting - origin easting, y = northing - origin northing "
                              "(x east, y grid north, metres of the UTM grid)"}


__all__ = ["WorldGeo", "utm_epsg"]
