"""``lidar``: rotating LiDARs on UEs, cast into the ray tracer's scene with the moving bodies.

Every sweep that starts within a step is cast (``rate_hz`` × Ts of them), each column from
where the sensor is when it fires: between the UE's last two positions, carried on at the
same velocity past the step's time. The other UEs are boxes in the scene: SUMO vehicles and
persons at their size and heading (``dimensions``, ``heading`` of their positions), UAVs as
``uav_body_m`` boxes; a sensor never sees its own UE's body. Per sweep it publishes:

- ``3D.lidar.<UE_Id>``: the point cloud, float32 (n, 6), the columns of
  :data:`~caviar_plugins.lidar.sensor.COLUMNS` (binary: a blueprint keeps it out of the
  recording with ``output.exclude = ["3D.lidar.*"]``, as camera images);
- ``3D.lidar.<UE_Id>.sweep``: when and where it started, the rays fired, returns and drops,
  and the names of the objects its ``object`` column indexes;
- with ``save_every = N``, every N-th sweep also as an ``.npz`` artifact on
  ``3D.lidar.<UE_Id>.file`` (recorded: ``caviar-core report`` draws the last one).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import numpy as np

import caviar
from caviar_plugins import limits
from caviar_plugins.lidar.sensor import COLUMNS, Caster, LidarSettings
from caviar_plugins.rt.scatterers import Body, ScattererPool
from caviar_plugins.rt.scene import build_scene, itu_material
from caviar_plugins.rt.settings import TraceSettings, moved_keys
from caviar_plugins.schema import ARRIVED, LIDAR, POSITIONS, VIEW_LIDAR, every_ue, per_ue, read_position

SWEEP = "sweep"
"""Last token of a sweep's metadata topic, ``3D.lidar.<UE_Id>.sweep``."""
FILE = "file"
"""Last token of a saved sweep's artifact topic, ``3D.lidar.<UE_Id>.file``."""


class Lidar(caviar.Plugin):
    subscribe = [POSITIONS, ARRIVED]
    optional = (ARRIVED,)  # (UEs that leave: SUMO's arrivals, when traffic runs)
    publishes = (every_ue(LIDAR), f"{every_ue(LIDAR)}.{SWEEP}", f"{every_ue(LIDAR)}.{FILE}", VIEW_LIDAR)

    @dataclasses.dataclass
    class Params:
        ue_ids: list[str] = dataclasses.field(default_factory=lambda: ["uav1"])
        """The UEs that carry a LiDAR."""
        scene: str = "central_park"
        """The ray tracer's scene: a shipped one, a Mitsuba XML file (``scene build``'s), or ``empty``."""
        sensor: LidarSettings = dataclasses.field(default_factory=LidarSettings)
        """``channels``, ``vertical_fov_deg``, ``horizontal_resolution_deg``, ``rate_hz``,
        ``max_range_m``, ``range_noise_m``, ``dropout``... (see
        :class:`~caviar_plugins.lidar.sensor.LidarSettings`)."""
        bodies: bool = True
        """The other UEs as boxes in the scene (vehicles, persons, UAVs)."""
        uav_body_m: tuple[float, float, float] = (1.0, 1.0, 0.4)
        """Length, width and height of a UAV's box, centred on its position."""
        raytracing: TraceSettings = dataclasses.field(default_factory=TraceSettings)
        """The ray tracer's settings (:class:`~caviar_plugins.rt.settings.TraceSettings`); a
        LiDAR casts one ray per beam (``sensor``), so only ``threads`` (Dr.Jit CPU threads,
        0 = all cores) applies."""
        save_every: int = 0
        """Also save every N-th sweep as an ``.npz`` artifact (points, columns, objects, origin, time; 0: none)."""
        view_points: int = 0
        """Draw each step's last sweep in the browser view (``view.lidar``), thinned to this
        many points, coloured by what they hit (0: not drawn)."""
        allow_large: bool = False
        """Lift the bounds on the rays of a sweep, the spin rate and the rays per second
        (:mod:`caviar_plugins.limits`), for a machine that can cast more."""

        moved: ClassVar[dict[str, str]] = moved_keys("threads")

        def __post_init__(self):
            given = caviar.given_keys()
            unused = [f"raytracing.{f.name}" for f in dataclasses.fields(TraceSettings) if f.name != "threads"
                      and (f"raytracing.{f.name}" in given if given is not None
                           else getattr(self.raytracing, f.name) != f.default)]
            if unused:
                raise ValueError(f"{unused[0]}: a LiDAR casts one ray per beam (see sensor); of raytracing only "
                                 f"threads applies")
            for key in ("save_every", "view_points"):
                v = getattr(self, key)
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ValueError(f"{key}: expected a whole number >= 0, got {v!r}")
            if not self.ue_ids or len(set(self.ue_ids)) != len(self.ue_ids):
                raise ValueError(f"ue_ids: expected one or more distinct UE ids, got {self.ue_ids!r}")
            if len(self.uav_body_m) != 3 or not all(v > 0 for v in self.uav_body_m):
                raise ValueError(f"uav_body_m: expected [length, width, height] > 0 in metres, got {self.uav_body_m!r}")
            s, allow = self.sensor, self.allow_large
            rays = s.channels * s.columns
            limits.bounded("sensor.channels" if s.channels > 1024 else "sensor.horizontal_resolution_deg", rays,
                           limits.LIDAR_RAYS_PER_SWEEP, f"a sweep of {s.channels} channels × {s.columns:,} columns",
                           allow, "rays")
            limits.bounded("sensor.rate_hz", s.rate_hz, limits.LIDAR_RATE_HZ, "the spin rate", allow, "Hz")
            limits.bounded("sensor.rate_hz", rays * s.rate_hz * len(self.ue_ids), limits.LIDAR_RAYS_PER_S,
                           f"{len(self.ue_ids)} LiDAR(s) of {rays:,} rays a sweep at {s.rate_hz:g} Hz", allow,
                           "rays a second")

    def setup(self, ctx):
        self.ctx = ctx
        p = self.p = ctx.params
        self.scene = build_scene(p.scene, ctx.config_dir, threads=p.raytracing.threads,
                                 merge_shapes=False)  # (objects by name)
        self.pool = ScattererPool(self.scene, {"vehicle": 8, "person": 8, "uav": 2}, {
            "vehicle": itu_material("lidar-vehicle", "metal", thickness=0.01),
            "person": itu_material("lidar-person", "wood", thickness=0.2),
            "uav": itu_material("lidar-uav", "metal", thickness=0.01),
        }, prefix="lidar")
        self.caster = Caster(self.scene, p.sensor, [self.pool])
        self.step_s = ctx.ts * ctx.every
        # Per UE: its last position, its velocity, the box it is (or None) -- the bodies.
        self.ues: dict[str, dict[str, Any]] = {}

    def state(self):
        # The scene and the pool's first boxes come from setup; its growth (replayed in
        # order), its boxes and where the UEs were are the state.
        return {"ues": self.ues, "pool_edits": list(self.pool.edit_log), "pool": self.pool.snapshot()}

    def restore(self, state):
        self.ues = state["ues"]
        for _, more in state["pool_edits"][len(self.pool.edit_log):]:
            self.pool.grow(more)
        self.pool.restore(state["pool"])

    def _read(self, t: float, inbox) -> None:
        for m in inbox.on(ARRIVED):
            self.ues.pop(m.data["UE_Id"], None)
        for m in inbox.on(POSITIONS):
            ue, pos = m.data["UE_Id"], read_position(m.data)
            old = self.ues.get(ue)
            velocity = [0.0, 0.0, 0.0]
            if old is not None and t > old["time"]:
                velocity = ((pos - np.array(old["position"])) / (t - old["time"])).tolist()
            dims = m.data.get("dimensions")
            if dims is not None:
                group = "person" if m.data.get("UE_type") == "pedestrian" else "vehicle"
                box = (group, pos.tolist(), float(m.data.get("heading", 0.0)),
                       [float(dims["length"]), float(dims["width"]), float(dims["height"])])
            else:
                size = [float(v) for v in self.p.uav_body_m]
                box = ("uav", (pos - [0.0, 0.0, size[2] / 2]).tolist(), 0.0, size)
            self.ues[ue] = {"time": t, "position": pos.tolist(), "velocity": velocity, "box": box}

    def _bodies(self, leave_out: str) -> list[Body]:
        if not self.p.bodies:
            return []
        return [Body(ue, u["box"][0], tuple(u["box"][1]), u["box"][2], tuple(u["box"][3]))
                for ue, u in sorted(self.ues.items()) if ue != leave_out]

    def step(self, t, inbox):
        self._read(t, inbox)
        s = self.p.sensor
        first = math.floor((t - self.step_s) * s.rate_hz + 1e-9) + 1
        last = math.floor(t * s.rate_hz + 1e-9)
        offset = np.asarray(s.mount_offset_m)
        drawn: list[dict] = []
        for ue in self.p.ue_ids:
            u = self.ues.get(ue)
            if u is None or last < first:
                continue
            self.pool.update(self._bodies(leave_out=ue), grow=True)
            here, velocity = np.array(u["position"]) + offset, np.array(u["velocity"])
            for k in range(first, last + 1):
                start = k / s.rate_hz
                fired = start + s.sweep_s * np.arange(s.columns) / s.columns
                origins = here + velocity * (fired - t)[:, None]
                sweep = self.caster.cast(origins, self.ctx.rng)
                yield per_ue(LIDAR, ue), sweep.points
                info = {"UE_Id": ue, "sweep": k, "time": round(start, 9),
                        "origin": [round(float(v), 4) for v in origins[0]], "rays": sweep.rays,
                        "points": int(len(sweep.points)), "dropped": sweep.dropped, "columns": list(COLUMNS),
                        "objects": sweep.objects}
                yield f"{per_ue(LIDAR, ue)}.{SWEEP}", info
                if self.p.save_every and k % self.p.save_every == 0:
                    path = self.ctx.artifact_dir / f"{ue}-lidar-{k:06d}.npz"
                    np.savez_compressed(path, points=sweep.points, columns=np.array(COLUMNS),
                                        objects=np.array(sweep.objects), origin=origins[0], time=start)
                    yield f"{per_ue(LIDAR, ue)}.{FILE}", caviar.Artifact(path)
                if k == last and self.p.view_points:
                    drawn += self._view_points(sweep)
        if drawn:
            yield VIEW_LIDAR, {"points": drawn}

    def _view_points(self, sweep) -> list[dict]:
        """Up to ``view_points`` of the sweep's points, evenly thinned: moving bodies red,
        the ground and roads green, the rest (buildings) grey."""
        pts = sweep.points[np.linspace(0, len(sweep.points) - 1, min(self.p.view_points, len(sweep.points)))
                           .astype(int)] if len(sweep.points) else sweep.points
        out = []
        for x, y, z, _, _, obj in pts:
            name = sweep.objects[int(obj)]
            low = name.lower()
            colour = "#ff5252" if name in self.ues else "#7cb342" if any(
                w in low for w in ("ground", "road", "plane", "floor", "terrain")) else "#b0bec5"
            out.append({"x": round(float(x), 2), "y": round(float(y), 2), "z": round(float(z), 2), "color": colour,
                        "size": 2})
        return out
