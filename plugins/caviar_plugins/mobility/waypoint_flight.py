"""UAV flight along waypoints."""

from __future__ import annotations

import dataclasses
import pathlib

import caviar
from caviar_plugins.assets import DATA
from caviar_plugins.mobility.frames import airsim_ned_to_scene
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.schema import HOVER, POSITIONS, position_payload


class WaypointFlight(caviar.Plugin):
    """Flies one UAV along waypoints at constant speed and publishes its position
    (paper schema) every step. It hovers while a ``mission.hover`` message for it
    says so, and ends the episode at the last waypoint if ``end_at_last``."""

    subscribe = [HOVER]
    publishes = (POSITIONS, caviar.END_TOPIC)

    @dataclasses.dataclass
    class Params:
        waypoints: str = "central_park_path0.csv"
        """CSV with header X,Y,Z: a path relative to the config file, or the name of a
        shipped trajectory (central_park_path0.csv: the paper's, AirSim NED;
        central_park_path0_scene.csv: scene frame, spur stopped before the building)."""
        frame: str = "airsim_ned"
        """``airsim_ned`` (converted to the scene frame) or ``scene``."""
        speed: float = 5.0
        """m/s"""
        ue_id: str = "uav1"
        end_at_last: bool = True
        start_m: float = 0.0
        """Distance along the route at which the UAV starts (to spread several UAVs)."""

        def __post_init__(self):
            if self.frame not in ("airsim_ned", "scene"):
                raise ValueError(f"frame: expected 'airsim_ned' or 'scene', got {self.frame!r}")
            if not self.speed > 0:
                raise ValueError(f"speed: expected a positive number of m/s, got {self.speed}")

    @staticmethod
    def _waypoint_file(waypoints: str, config_dir) -> pathlib.Path:
        """The CSV: relative to the config file, else a shipped trajectory."""
        path = pathlib.Path(config_dir) / waypoints
        if not path.exists() and (DATA / waypoints).exists():
            path = DATA / waypoints
        return path

    @classmethod
    def check_params(cls, params, config_dir):
        path = cls._waypoint_file(params.waypoints, config_dir)
        if not path.is_file():
            raise ValueError(f"waypoints: no such file: {path} (nor a shipped trajectory of that name)")

    def setup(self, ctx):
        p = ctx.params
        path = self._waypoint_file(p.waypoints, ctx.config_dir)
        pts = read_waypoints(path)
        if p.frame == "airsim_ned":
            pts = airsim_ned_to_scene(pts)
        self.path = Path(pts)
        self.p = p
        self.s = min(max(p.start_m, 0.0), self.path.length)  # arc length flown
        self.hover_until = -1.0
        self.ts = ctx.ts

    def step(self, t, inbox):
        for m in inbox.on(HOVER):
            if m.data.get("UE_Id") == self.p.ue_id:
                self.hover_until = max(self.hover_until, t + float(m.data["seconds"]))
        yield POSITIONS, position_payload(self.p.ue_id, self.path.at(self.s))
        if self.s >= self.path.length and self.p.end_at_last:
            yield caviar.END_TOPIC, {"reason": f"{self.p.ue_id} reached its last waypoint"}
        if t + 1e-9 >= self.hover_until:
            self.s += self.p.speed * self.ts
