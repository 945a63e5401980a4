"""UAV flight between random waypoints around a route (the beam-selection dataset's)."""

from __future__ import annotations

import dataclasses

import numpy as np

import caviar
from caviar_plugins.assets import DATA
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.schema import POSITIONS, position_payload


class RandomWaypointFlight(caviar.Plugin):
    """A UAV flying at constant speed between random waypoints: each is a random point
    of the route moved sideways by up to ``spread`` metres, at a random altitude."""

    publishes = (POSITIONS,)

    @dataclasses.dataclass
    class Params:
        route: str = "central_park_path0_scene.csv"
        spread: float = 15.0
        altitude: list[float] = dataclasses.field(default_factory=lambda: [8.0, 12.0])
        speed: float = 5.0
        ue_id: str = "uav1"

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        path = ctx.resolve(p.route)
        self.route = Path(read_waypoints(path if path.exists() else DATA / p.route))
        self.pos = self._waypoint()
        self.target = self._waypoint()

    def state(self):
        # The waypoints still to come are drawn from ctx.rng, which the host saves.
        return {"pos": self.pos, "target": self.target}

    def restore(self, state):
        self.pos, self.target = state["pos"], state["target"]

    def _waypoint(self) -> np.ndarray:
        rng, p = self.ctx.rng, self.ctx.params
        on_route = self.route.at(rng.uniform(0, self.route.length))
        return np.r_[on_route[:2] + rng.uniform(-p.spread, p.spread, 2), rng.uniform(*p.altitude)]

    def step(self, t, inbox):
        p = self.ctx.params
        yield POSITIONS, position_payload(p.ue_id, self.pos)
        move = p.speed * self.ctx.ts
        while move > 0:
            d = self.target - self.pos
            dist = float(np.linalg.norm(d))
            if dist > move:
                self.pos = self.pos + d / dist * move
                break
            self.pos, move = self.target, move - dist
            self.target = self._waypoint()
