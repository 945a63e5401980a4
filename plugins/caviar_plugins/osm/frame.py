"""The scene frame: x east, y north, z up, metres, origin at a point on the ground.

A transverse Mercator projection centred on the origin (scale 1 there): within a few
kilometres distances are true to better than 1e-5 and grid north is true north. The
same PROJ string goes into ``scene.json`` and, with ``--sumo``, to netconvert, so both
share one frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


def proj_string(lat: float, lon: float) -> str:
    return (f"+proj=tmerc +lat_0={lat:.9f} +lon_0={lon:.9f} +k=1 +x_0=0 +y_0=0 "
            "+ellps=WGS84 +towgs84=0,0,0,0,0,0,0 +units=m +no_defs")


@dataclasses.dataclass
class Frame:
    lat: float
    lon: float

    def __post_init__(self):
        from pyproj import Transformer

        self.proj = proj_string(self.lat, self.lon)
        self._fwd = Transformer.from_crs("EPSG:4326", self.proj, always_xy=True)
        self._inv = Transformer.from_crs(self.proj, "EPSG:4326", always_xy=True)

    def to_xy(self, lon, lat) -> tuple[np.ndarray, np.ndarray]:
        """Longitudes and latitudes (degrees) to scene x, y (metres)."""
        return self._fwd.transform(np.asarray(lon, dtype=float), np.asarray(lat, dtype=float))

    def to_lonlat(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        return self._inv.transform(np.asarray(x, dtype=float), np.asarray(y, dtype=float))


@dataclasses.dataclass(frozen=True)
class BBox:
    south: float
    west: float
    north: float
    east: float

    @classmethod
    def parse(cls, text: str) -> "BBox":
        try:
            s, w, n, e = (float(v) for v in text.split(","))
        except ValueError:
            raise ValueError(f"--bbox: expected S,W,N,E in degrees, got {text!r}") from None
        return cls(s, w, n, e).checked()

    @classmethod
    def around(cls, lat: float, lon: float, radius_m: float) -> "BBox":
        """The square (in the local frame) enclosing the circle of radius_m around lat, lon."""
        if not radius_m > 0:
            raise ValueError(f"--radius: expected a positive number of metres, got {radius_m}")
        f = Frame(lat, lon)
        lon_w, lat_s = f.to_lonlat(-radius_m, -radius_m)
        lon_e, lat_n = f.to_lonlat(radius_m, radius_m)
        return cls(float(lat_s), float(lon_w), float(lat_n), float(lon_e)).checked()

    def checked(self) -> "BBox":
        if not (-90 <= self.south < self.north <= 90 and -180 <= self.west < self.east <= 180):
            raise ValueError(f"empty or invalid bbox S,W,N,E = {self.south},{self.west},{self.north},{self.east}"
                             " (needs S < N and W < E, in degrees)")
        return self

    @property
    def centre(self) -> tuple[float, float]:
        return (self.south + self.north) / 2, (self.west + self.east) / 2

    def contains(self, lon, lat) -> np.ndarray:
        lon, lat = np.asarray(lon), np.asarray(lat)
        return (lat >= self.south) & (lat <= self.north) & (lon >= self.west) & (lon <= self.east)

    def as_list(self) -> list[float]:
        return [self.south, self.west, self.north, self.east]


def approx_size_m(b: BBox) -> tuple[float, float]:
    """East-west and north-south extent in metres (spherical approximation; messages only)."""
    r = 6_371_000.0
    lat = math.radians((b.south + b.north) / 2)
    return (math.radians(b.east - b.west) * r * math.cos(lat), math.radians(b.north - b.south) * r)
