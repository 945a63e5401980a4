"""The beam-selection dataset (Mob+3D/Comm-in-loop, no AI in the loop), like Raymobtime:
one npz record per step with the UAV position, the best beam pair, the LOS flag and
the gains of all pairs.

* :class:`RandomWaypointFlight` flies between random waypoints drawn around the route.
* :class:`BeamDataset` writes ``RUN_DIR/artifacts/NAME/step-NNNNNN-UE.npz``.
* :func:`load` reads a run's records back as arrays.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

import caviar
from caviar_plugins import DATA
from caviar_plugins.frames import read_waypoints
from caviar_plugins.mobility import POSITIONS, Path


class RandomWaypointFlight(caviar.Plugin):
    """A UAV flying at constant speed between random waypoints: each is a random point
    of the route moved sideways by up to ``spread`` metres, at a random altitude."""

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

    def _waypoint(self) -> np.ndarray:
        rng, p = self.ctx.rng, self.ctx.params
        on_route = self.route.at(rng.uniform(0, self.route.length))
        return np.r_[on_route[:2] + rng.uniform(-p.spread, p.spread, 2), rng.uniform(*p.altitude)]

    def step(self, t, inbox):
        p = self.ctx.params
        yield POSITIONS, {"UE_type": "UAV", "UE_Id": p.ue_id,
                          "position": {"x": float(self.pos[0]), "y": float(self.pos[1]), "z": float(self.pos[2])}}
        move = p.speed * self.ctx.ts
        while move > 0:
            d = self.target - self.pos
            dist = float(np.linalg.norm(d))
            if dist > move:
                self.pos = self.pos + d / dist * move
                break
            self.pos, move = self.target, move - dist
            self.target = self._waypoint()


class BeamDataset(caviar.Plugin):
    """Writes one npz record per UAV and step: position, best pair, LOS, gains."""

    subscribe = [POSITIONS, "communications.link", "communications.beam_gains.*"]

    def setup(self, ctx):
        self.ctx = ctx
        self.positions: dict[str, list[float]] = {}

    def step(self, t, inbox):
        for m in inbox.on(POSITIONS):
            p = m.data["position"]
            self.positions[m.data["UE_Id"]] = [p["x"], p["y"], p["z"]]
        links = {m.data["UE_Id"]: m.data for m in inbox.on("communications.link")}
        for m in inbox.on("communications.beam_gains.*"):
            ue = m.topic.rsplit(".", 1)[1]
            path = self.ctx.artifact_dir / f"step-{self.ctx.step:06d}-{ue}.npz"
            np.savez(path, position=np.array(self.positions[ue]), best_pair=links[ue]["best_pair"],
                     los=links[ue]["los"], gains=m.data, time=t)
            yield "dataset.record", caviar.Artifact(path)


def load(run_dir: str | pathlib.Path) -> dict[str, np.ndarray]:
    """All records of a run: position (N, 3), best_pair (N,), los (N,), gains (N, 4, 64)."""
    files = sorted(pathlib.Path(run_dir).glob("artifacts/*/step-*.npz"))
    if not files:
        raise FileNotFoundError(f"{run_dir}: no dataset records (artifacts/*/step-*.npz)")
    records = [np.load(f) for f in files]
    return {k: np.stack([r[k] for r in records]) for k in ("position", "best_pair", "los", "gains")}
