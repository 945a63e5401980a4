"""The ``sumo-traffic`` mobility plugin: SUMO in lockstep with the engine.

Every step SUMO advances to the engine's time (``substeps`` SUMO steps of Ts/substeps)
and every vehicle and person in the network is published on ``3D.mobility.positions``
(paper schema; ``UE_Id`` = SUMO id) with extra fields::

    {"UE_type": "car", "UE_Id": "passenger3", "position": {"x", "y", "z"},
     "heading": 1.57, "speed": 8.3, "velocity": {"x", "y", "z"},
     "dimensions": {"length": 5.0, "width": 1.8, "height": 1.5}, "vclass": "passenger"}

``position`` is the centre of the footprint on the ground (scene frame: SUMO coordinates
of a network built by ``caviar-core scene build --sumo`` are scene coordinates),
``heading`` radians counter-clockwise from x (east), ``speed`` m/s. Departures and
arrivals are announced on ``3D.mobility.departed`` / ``3D.mobility.arrived``, and a
per-step summary with SUMO's clock on ``3D.mobility.traffic``.

The plugin keeps everything it needs in its own process (SUMO included), so it runs
in-process or in a NATS worker alike.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import sys
from typing import Optional

import caviar
from caviar_plugins.schema import ARRIVED, DEPARTED, POSITIONS, TRAFFIC, position_payload
from caviar_plugins.traffic.demand import random_trips
from caviar_plugins.traffic.sumo import VEHICLE_CLASSES, Sumo, SumoError

BACKENDS = ("libsumo", "traci", "traci-connect")

STATE_PRECISION = 17
"""Digits SUMO writes in a saved state: enough that a loaded state goes on as the saved run."""


@dataclasses.dataclass
class SumoTrafficParams:
    net: str = ""
    """The SUMO network (``net.net.xml`` or ``.net.xml.gz``), relative to the config file."""
    routes: list[str] = dataclasses.field(default_factory=list)
    """The user's route files (vehicles, persons, vTypes), added to the random demand."""
    vehicles: Optional[dict] = None
    """Random vehicles per SUMO vehicle class, e.g. ``{passenger = 45, bus = 5}``.
    Default ``{passenger = 50}`` without ``routes``, none with them."""
    pedestrians: Optional[int] = None
    """Random pedestrians (walks). Default 20 without ``routes``, none with them."""
    window_s: float = 10.0
    """Random departures are spread over [0, window_s)."""
    min_trip_m: float = 300.0
    """Shortest random trip (straight line), so that vehicles stay a while."""
    substeps: int = 1
    """SUMO steps per engine step: SUMO's step length is Ts · every / substeps."""
    backend: str = "libsumo"
    """``libsumo`` (in-process, default), ``traci`` (starts ``sumo`` or ``sumo-gui`` and
    talks TraCI) or ``traci-connect`` (connects to a SUMO started by the user with
    ``--remote-port PORT``; the SUMO options here are then the user's business)."""
    gui: bool = False
    """With ``backend = "traci"``: run ``sumo-gui`` instead of ``sumo``."""
    port: int = 0
    host: str = "localhost"
    sumo_args: list[str] = dataclasses.field(default_factory=list)
    """More SUMO options, e.g. ``["--time-to-teleport", "60"]``."""
    end_when_empty: bool = False
    """End the episode once every vehicle and person has arrived."""

    def __post_init__(self):
        if not self.net and self.backend != "traci-connect":
            raise ValueError("net: the SUMO network file is required (e.g. scene/net.net.xml from "
                             "`caviar-core scene build ... --sumo`)")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend: expected one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.vehicles is None:
            self.vehicles = {} if self.routes else {"passenger": 50}
        if self.pedestrians is None:
            self.pedestrians = 0 if self.routes else 20
        for vclass, n in self.vehicles.items():
            if vclass not in VEHICLE_CLASSES:
                raise ValueError(f"vehicles: unknown vehicle class {vclass!r}; SUMO's classes are "
                                 f"{', '.join(VEHICLE_CLASSES)}")
            if not isinstance(n, int) or isinstance(n, bool) or n < 0:
                raise ValueError(f"vehicles.{vclass}: expected a count >= 0, got {n!r}")
        if self.pedestrians < 0:
            raise ValueError(f"pedestrians: expected a count >= 0, got {self.pedestrians}")
        if self.substeps < 1:
            raise ValueError(f"substeps: expected >= 1, got {self.substeps}")
        if not self.window_s > 0:
            raise ValueError(f"window_s: expected > 0, got {self.window_s}")


class SumoTraffic(caviar.Plugin):
    publishes = (POSITIONS, DEPARTED, ARRIVED, TRAFFIC, caviar.END_TOPIC)
    Params = SumoTrafficParams

    @classmethod
    def check_params(cls, params, config_dir):
        """The network and route files exist (``validate`` catches them; whether SUMO
        accepts them is known only when it loads them, in setup)."""
        base = pathlib.Path(config_dir)
        if params.net and not (base / params.net).is_file():
            raise caviar.ConfigError(f"{base / params.net}: no such SUMO network file", "net")
        for i, r in enumerate(params.routes):
            if not (base / r).is_file():
                raise caviar.ConfigError(f"{base / r}: no such route file", f"routes[{i}]")

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.p = p
        self.dt = ctx.ts * ctx.every / p.substeps
        net = ctx.resolve(p.net).resolve() if p.net else None
        routes = [ctx.resolve(r).resolve() for r in p.routes]
        if net is not None and not net.is_file():
            raise caviar.ConfigError(f"{net}: no such SUMO network file", "params.net")
        for i, r in enumerate(routes):
            if not r.is_file():
                raise caviar.ConfigError(f"{r}: no such route file", f"params.routes[{i}]")
        work = ctx.artifact_dir
        seed = ctx.seed % 2**31
        if net is not None and p.backend != "traci-connect" and (sum(p.vehicles.values()) or p.pedestrians):
            try:
                routes += random_trips(net, work / "demand", p.vehicles, p.pedestrians, seed, p.window_s,
                                       p.min_trip_m)
            except SumoError as e:
                raise caviar.ConfigError(str(e), "params.net") from None
        args = []
        if p.backend != "traci-connect":
            # A checkpoint's saved state keeps SUMO's random streams and full precision.
            args = ["-n", str(net), "--step-length", repr(self.dt), "--begin", "0", "--seed", str(seed),
                    "--route-steps", "0", "--no-step-log", "true", "--no-warnings", "true",
                    "--duration-log.disable", "true", "--save-state.rng", "true", "--save-state.transportables", "true",
                    "--save-state.precision", str(STATE_PRECISION), *p.sumo_args]
            if routes:
                args += ["-r", ",".join(str(r) for r in routes)]
        try:
            self.sumo = Sumo(args, work / "sumo.log", backend=p.backend, binary_name="sumo-gui" if p.gui else "sumo",
                             port=p.port, host=p.host, label=f"caviar-{ctx.name}")
        except SumoError as e:
            if p.backend == "traci-connect":
                raise caviar.ConfigError(f"no SUMO to connect to at {p.host}:{p.port} (start it with "
                                         f"`sumo-gui --remote-port {p.port} ...`): {e}", "params.port") from None
            user = ", ".join(str(f) for f in [net, *routes[:len(p.routes)]] if f is not None)
            key = "params.routes" if p.routes else "params.net"
            raise caviar.ConfigError(f"SUMO cannot load {user}: {e}", key) from None
        self.kind: dict[str, str] = {}

    def step(self, t, inbox):
        departed, arrived = self.sumo.advance_to(t, self.dt)
        now = self.sumo.time
        if abs(now - t) > 1e-6 * max(1.0, t):
            raise RuntimeError(f"SUMO's clock ({now} s) is not the engine's ({t} s): its step length "
                               f"{self.dt} s does not divide the time between steps")
        entities = self.sumo.entities()
        for e in entities:
            self.kind[e.id] = e.ue_type
        for ids, topic in ((departed, DEPARTED), (arrived, ARRIVED)):
            for eid in ids:
                yield topic, {"UE_type": self.kind.get(eid, "vehicle"), "UE_Id": eid}
        for e in entities:
            msg = position_payload(e.id, e.xyz, e.ue_type)
            vx, vy, vz = e.velocity
            msg.update(heading=_r(e.yaw), speed=_r(e.speed), velocity={"x": _r(vx), "y": _r(vy), "z": _r(vz)},
                       dimensions={"length": e.length, "width": e.width, "height": e.height}, vclass=e.vclass)
            yield POSITIONS, msg
        n_persons = sum(e.ue_type == "pedestrian" for e in entities)
        yield TRAFFIC, {"sumo_time": now, "vehicles": len(entities) - n_persons, "persons": n_persons,
                        "departed": len(departed), "arrived": len(arrived)}
        for eid in arrived:
            self.kind.pop(eid, None)
        if self.p.end_when_empty and t > 0 and self.sumo.api.simulation.getMinExpectedNumber() == 0:
            yield caviar.END_TOPIC, {"reason": "every vehicle and person has arrived"}

    def state(self):
        # SUMO's own saved state (vehicles, persons, routes, random streams), as bytes.
        if self.p.backend == "traci-connect":
            raise RuntimeError("a SUMO this run connected to (backend = 'traci-connect') is not the run's to save")
        return {"sumo": self.sumo.save_state(self.ctx.artifact_dir / "checkpoint.sumo-state.xml"),
                "kind": self.kind}

    def restore(self, state):
        self.sumo.load_state(self.ctx.artifact_dir / "checkpoint.sumo-state.xml", state["sumo"])
        self.kind = state["kind"]
        if b"<person " in state["sumo"]:
            # Measured with SUMO 1.28: vehicles go on exactly, pedestrians (striping model) do not.
            print(f"{self.ctx.name} (sumo-traffic): warning: SUMO's saved state does not hold its pedestrian "
                  "model's own state: after this resume pedestrians walk on from where they were, but not "
                  "exactly as in an uninterrupted run (vehicles do)", file=sys.stderr, flush=True)

    def teardown(self):
        sumo = getattr(self, "sumo", None)
        if sumo is not None:
            sumo.close()


def _r(v: float) -> float:
    return round(float(v), 6) if math.isfinite(v) else 0.0
