"""A rotating multi-beam LiDAR cast into the ray tracer's own scene.

The sensor spins about its vertical axis at ``rate_hz``. A sweep fires ``channels`` beams
(elevations evenly spread over ``vertical_fov_deg``) at each of 360 / ``horizontal_resolution_deg``
azimuths, one azimuth after the other, so a sensor that moves during the sweep fires each
column from where it is then (the motion distortion of a real rotating LiDAR). Each beam is
one ray into the Mitsuba scene of Sionna RT (:func:`~caviar_plugins.rt.scene.load_scene`,
the scene the radio traces) with the moving bodies of a
:class:`~caviar_plugins.rt.scatterers.ScattererPool` in it (SUMO vehicles and persons, other
UAVs), so the LiDAR sees what the radio sees.

A return has the point where the ray met the first surface, a range with Gaussian noise
(``range_noise_m``), an intensity (the surface's reflectivity at 905 nm, from its material,
times the cosine of the incidence angle: a Lambertian target), the ring (channel) and the
object hit. Returns beyond ``max_range_m`` or nearer than ``min_range_m`` are none, and each
return is dropped with probability ``dropout``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from caviar_plugins.rt.scene import surface_hits

REFLECTIVITY = {"concrete": 0.35, "brick": 0.3, "plasterboard": 0.6, "wood": 0.4, "glass": 0.05,
                "ceiling_board": 0.6, "chipboard": 0.4, "plywood": 0.4, "marble": 0.5, "floorboard": 0.4,
                "metal": 0.6, "very_dry_ground": 0.25, "medium_dry_ground": 0.2, "wet_ground": 0.1,
                "vehicle": 0.6, "person": 0.3, "uav": 0.5}
"""Diffuse reflectivity at 905 nm by material (ITU type, or a body's group): typical values of
the LiDAR literature (concrete 0.3–0.4, painted metal 0.5–0.7, glass near 0 off normal
incidence); any other material 0.3."""
DEFAULT_REFLECTIVITY = 0.3
COLUMNS = ("x", "y", "z", "intensity", "ring", "object")
"""The columns of a point cloud (float32, one row per return): the point in the scene frame
(m), the intensity (0..1), the channel (0 = lowest beam) and the index of the object hit in
the sweep's ``objects`` list."""


@dataclasses.dataclass(frozen=True)
class LidarSettings:
    channels: int = 32
    """Beams (rings), evenly spread over the vertical field of view."""
    vertical_fov_deg: tuple[float, float] = (-30.67, 10.67)
    """The lowest and the highest beam's elevation above the horizontal (a Velodyne HDL-32E's
    by default)."""
    horizontal_resolution_deg: float = 0.2
    """Azimuth step: 1,800 columns per sweep at 0.2°."""
    rate_hz: float = 10.0
    """Sweeps per second (the spin rate)."""
    max_range_m: float = 100.0
    min_range_m: float = 0.5
    range_noise_m: float = 0.02
    """Standard deviation of the Gaussian range error."""
    dropout: float = 0.0
    """The probability that a return is lost (dark or specular surfaces, rain)."""
    mount_offset_m: tuple[float, float, float] = (0.0, 0.0, -0.3)
    """Where the sensor sits relative to the UE's reported position (below a UAV's body)."""
    yaw_deg: float = 0.0
    """Azimuth of the first column, counter-clockwise from x (east)."""

    def __post_init__(self):
        if isinstance(self.channels, bool) or not isinstance(self.channels, int) or self.channels < 1:
            raise ValueError(f"channels: expected a whole number of beams >= 1, got {self.channels!r}")
        lo, hi = (float(v) for v in self.vertical_fov_deg)
        if not (-90.0 <= lo <= hi <= 90.0):
            raise ValueError(f"vertical_fov_deg: expected [lowest, highest] elevations within [-90, 90] degrees "
                             f"(a vertical field of view of at most 180°), got {list(self.vertical_fov_deg)}")
        if self.channels > 1 and lo == hi:
            raise ValueError(f"vertical_fov_deg: {self.channels} channels need a field of view wider than 0°")
        step = self.horizontal_resolution_deg
        if not 0 < step <= 360 or not float(360 / step).is_integer():
            raise ValueError(f"horizontal_resolution_deg: expected a step that divides 360°, "
                             f"got {self.horizontal_resolution_deg!r}")
        for key in ("rate_hz", "max_range_m"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key}: expected a positive number, got {v!r}")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError(f"min_range_m: expected metres in [0, max_range_m), got {self.min_range_m!r}")
        if not self.range_noise_m >= 0:
            raise ValueError(f"range_noise_m: expected a standard deviation >= 0 m, got {self.range_noise_m!r}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"dropout: expected a probability in [0, 1), got {self.dropout!r}")
        if len(self.mount_offset_m) != 3:
            raise ValueError(f"mount_offset_m: expected [x, y, z] in metres, got {self.mount_offset_m!r}")
        object.__setattr__(self, "vertical_fov_deg", (lo, hi))
        object.__setattr__(self, "mount_offset_m", tuple(float(v) for v in self.mount_offset_m))

    @property
    def columns(self) -> int:
        return round(360 / self.horizontal_resolution_deg)

    @property
    def sweep_s(self) -> float:
        return 1.0 / self.rate_hz

    def elevations_deg(self) -> np.ndarray:
        lo, hi = self.vertical_fov_deg
        return np.linspace(lo, hi, self.channels) if self.channels > 1 else np.array([lo])

    def directions(self) -> np.ndarray:
        """Unit vectors (columns, channels, 3) in the scene frame: column-major, the order
        the beams fire in."""
        el = np.radians(self.elevations_deg())[None, :]
        az = np.radians(self.yaw_deg + self.horizontal_resolution_deg * np.arange(self.columns))[:, None]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)


@dataclasses.dataclass
class Sweep:
    """One sweep's returns: ``points`` (n, 6) float32 with :data:`COLUMNS`, ``objects`` the
    names the ``object`` column indexes, and the rays fired and returns dropped."""

    points: np.ndarray
    objects: list[str]
    rays: int
    dropped: int


class Caster:
    """Casts sweeps into a Sionna RT ``scene`` (its Mitsuba scene) with the bodies of
    ``pools`` in it. ``names`` and ``reflectivity`` of each shape come from the scene's
    objects (their radio material) and, for a pool's mesh, from whose box is hit."""

    def __init__(self, scene: Any, settings: LidarSettings, pools: Sequence[Any] = ()):
        self.scene, self.s, self.pools = scene, settings, list(pools)
        self.directions = settings.directions().reshape(-1, 3)

    def _shapes(self) -> tuple[dict[int, str], dict[int, float], dict[int, Any]]:
        """Per Mitsuba shape id: its object's name, reflectivity and (for a pool mesh) pool."""
        names, refl, pool_of = {}, {}, {}
        for name, obj in self.scene.objects.items():
            oid = int(obj.object_id)
            names[oid] = name
            material = getattr(obj.radio_material, "itu_type", None) or obj.radio_material.name
            refl[oid] = REFLECTIVITY.get(str(material), DEFAULT_REFLECTIVITY)
        for pool in self.pools:
            for group, mesh in pool.meshes.items():
                oid = int(mesh.object_id)
                refl[oid], pool_of[oid] = REFLECTIVITY.get(group, DEFAULT_REFLECTIVITY), pool
        return names, refl, pool_of

    def cast(self, origins: np.ndarray, rng: np.random.Generator) -> Sweep:
        """A sweep fired from ``origins``: (columns, 3), where the sensor is at each column."""
        s = self.s
        n_ch = s.channels
        o = np.repeat(np.asarray(origins, dtype=np.float32), n_ch, axis=0)
        d = self.directions.astype(np.float32)
        hit, t_np, shape_np, normal, prim = surface_hits(self.scene, o, d, s.max_range_m)
        hit_np = hit & (t_np >= s.min_range_m)
        cosine = np.abs(np.einsum("ij,ij->i", normal, d))
        if s.range_noise_m > 0:
            t_np = t_np + rng.normal(0.0, s.range_noise_m, t_np.shape)
        keep = hit_np & (rng.random(t_np.shape) >= s.dropout) if s.dropout > 0 else hit_np
        dropped = int((hit_np & ~keep).sum())
        idx = np.flatnonzero(keep)
        if len(idx) == 0:
            return Sweep(points=np.zeros((0, len(COLUMNS)), dtype=np.float32), objects=[], rays=len(d),
                         dropped=dropped)
        names, refl, pool_of = self._shapes()
        sid = shape_np[idx]
        # Who is hit: a scene object by its shape, a pool's box by its shape and slot (12
        # triangles a box); labelled once per distinct (shape, slot).
        slot = np.where(np.isin(sid, list(pool_of)), prim[idx] // 12, -1)
        keys, which = np.unique(sid * (1 << 24) + (slot + 1), return_inverse=True)
        pairs = np.stack([keys >> 24, (keys & ((1 << 24) - 1)) - 1], -1)
        labels = []
        for shape_id, box in pairs:
            pool = pool_of.get(int(shape_id))
            key = pool.key_at(int(shape_id), 12 * int(box)) if pool is not None else None
            labels.append(key if key is not None else names.get(int(shape_id), "?"))
        objects = sorted(set(labels))
        object_of_pair = np.array([objects.index(name) for name in labels], dtype=np.float32)
        reflectivity = np.array([refl.get(int(shape_id), DEFAULT_REFLECTIVITY) for shape_id, _ in pairs])
        points = np.empty((len(idx), len(COLUMNS)), dtype=np.float32)
        points[:, :3] = o[idx] + d[idx] * t_np[idx, None]
        points[:, 3] = reflectivity[which.ravel()] * cosine[idx]
        points[:, 4] = idx % n_ch
        points[:, 5] = object_of_pair[which.ravel()]
        return Sweep(points=points, objects=objects, rays=len(d), dropped=dropped)
