"""From a vehicle's coordinates to the scene frame (x east, y north, z up, metres).

Two horizontal frames, chosen by :func:`load_frame`:

* :class:`ProjFrame`: the scene's own projection, the PROJ string of the ``scene.json``
  that ``caviar-core scene build`` writes next to ``scene.xml`` (a transverse Mercator
  centred on the scene's origin), through pyproj (the ``osm`` extra). Without pyproj the
  same scene falls back to :class:`EnuFrame` at the scene's origin: the two agree to
  better than 0.1 mm within 2 km of it.
* :class:`EnuFrame`: the local tangent plane (east, north) at a stated origin on the
  WGS84 ellipsoid, for scenes without ``scene.json`` (the shipped ``central_park``).

Heights are not projected: a scene's ground is flat at z = 0, so z is an altitude
difference (see ``altitude`` of the plugin), and the Earth's curvature (8 cm at 1 km
from the origin) is not subtracted. Points are projected from the ellipsoid's surface
(height 0), as map projections do.
"""

from __future__ import annotations

import json
import math
import pathlib
from typing import Protocol

WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563
WGS84_E2 = WGS84_F * (2 - WGS84_F)


class Frame(Protocol):
    description: str

    def to_xy(self, lat: float, lon: float) -> tuple[float, float]:
        """Latitude, longitude (degrees) to scene x (east), y (north) in metres."""
        ...


def ecef(lat: float, lon: float, h: float = 0.0) -> tuple[float, float, float]:
    """Earth-centred, Earth-fixed coordinates (m) of a WGS84 point (degrees, metres)."""
    phi, lam = math.radians(lat), math.radians(lon)
    sp, cp = math.sin(phi), math.cos(phi)
    n = WGS84_A / math.sqrt(1 - WGS84_E2 * sp * sp)
    return ((n + h) * cp * math.cos(lam), (n + h) * cp * math.sin(lam), (n * (1 - WGS84_E2) + h) * sp)


class EnuFrame:
    """East and north of the local tangent plane at ``(lat0, lon0)`` on the ellipsoid."""

    def __init__(self, lat0: float, lon0: float):
        if not (-90 < lat0 < 90 and -180 <= lon0 <= 180):
            raise ValueError(f"origin: expected a latitude in (-90, 90) and a longitude in [-180, 180], "
                             f"got {lat0}, {lon0}")
        self.lat0, self.lon0 = lat0, lon0
        self.x0, self.y0, self.z0 = ecef(lat0, lon0)
        phi, lam = math.radians(lat0), math.radians(lon0)
        self._east = (-math.sin(lam), math.cos(lam), 0.0)
        self._north = (-math.sin(phi) * math.cos(lam), -math.sin(phi) * math.sin(lam), math.cos(phi))
        self.description = f"local tangent plane (ENU) at {lat0:.7f}, {lon0:.7f}"

    def to_xy(self, lat: float, lon: float) -> tuple[float, float]:
        x, y, z = ecef(lat, lon)
        d = (x - self.x0, y - self.y0, z - self.z0)
        e, n = self._east, self._north
        return (e[0] * d[0] + e[1] * d[1] + e[2] * d[2], n[0] * d[0] + n[1] * d[1] + n[2] * d[2])


class ProjFrame:
    """A PROJ string's projection (pyproj), longitude/latitude in WGS84."""

    def __init__(self, proj: str, source: str = "PROJ"):
        from pyproj import Transformer

        self._fwd = Transformer.from_crs("EPSG:4326", proj, always_xy=True)
        self.proj = proj
        self.description = f"{source}: {proj}"

    def to_xy(self, lat: float, lon: float) -> tuple[float, float]:
        x, y = self._fwd.transform(lon, lat)
        return float(x), float(y)


def scene_json(scene: str, base: pathlib.Path) -> pathlib.Path:
    """The ``scene.json`` of a scene given as its folder, its ``scene.xml`` or the JSON
    itself (relative to ``base``), or of a shipped scene by name."""
    from caviar_plugins.assets import SCENES

    p = pathlib.Path(scene)
    if not p.is_absolute():
        p = base / p
    if not p.exists() and (SCENES / scene).is_dir():
        p = SCENES / scene
    candidate = p / "scene.json" if p.is_dir() else p if p.suffix == ".json" else p.with_name("scene.json")
    if not candidate.is_file():
        raise ValueError(f"scene: no scene.json at {candidate}: only a scene built by `caviar-core scene build` "
                         "carries its geodetic frame; for another scene (the shipped central_park) give "
                         "origin = [lat, lon, alt] instead")
    return candidate


def load_frame(scene: str, origin: list[float], base: pathlib.Path) -> tuple[Frame, float | None]:
    """The horizontal frame and the altitude AMSL of the scene's z = 0 (None: not known)
    from the plugin's ``scene`` and ``origin`` parameters: the scene's ``scene.json``
    (:func:`scene_json`; ``origin``, if given too, must be the scene's own and only adds
    its altitude), else the tangent plane at ``origin`` (:class:`EnuFrame`)."""
    if scene:
        path = scene_json(scene, base)
        try:
            info = json.loads(path.read_text())
            proj, lat0, lon0 = info["proj"], float(info["origin"]["lat"]), float(info["origin"]["lon"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"scene: {path} has no usable 'proj' and 'origin' ({type(e).__name__}: {e})") from None
        if origin and (len(origin) not in (2, 3) or abs(origin[0] - lat0) > 1e-6 or abs(origin[1] - lon0) > 1e-6):
            raise ValueError(f"origin: with scene = {scene!r} the origin is the scene's ({lat0}, {lon0}, from "
                             f"{path}); give origin = [{lat0}, {lon0}, ALT] only to state its altitude, or "
                             f"leave it out (got {origin})")
        alt = origin[2] if len(origin) == 3 else info["origin"].get("alt")
        try:
            return ProjFrame(proj, str(path)), alt
        except ImportError:  # pyproj is the osm extra's; the tangent plane is the same to < 0.1 mm
            return EnuFrame(lat0, lon0), alt
    if len(origin) not in (2, 3):
        raise ValueError("origin: expected [lat, lon] or [lat, lon, alt] (degrees, metres AMSL), "
                         f"got {origin}")
    return EnuFrame(origin[0], origin[1]), (origin[2] if len(origin) == 3 else None)
