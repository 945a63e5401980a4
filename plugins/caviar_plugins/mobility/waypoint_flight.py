"""UAV flight along waypoints."""

from __future__ import annotations

import copy
import dataclasses
import math
import pathlib

import numpy as np

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.assets import DATA
from caviar_plugins.mobility.frames import airsim_ned_to_scene
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.schema import FORECAST, HOVER, POSITIONS, RETURN_HOME, position_payload


class WaypointFlight(caviar.Plugin):
    """Flies one UAV along waypoints and publishes its position (paper schema) every
    step.

    ``protocol = "physical"``: constant speed through the waypoints; it hovers while a
    ``mission.hover`` message for it says so, and ends the episode at the last waypoint
    if ``end_at_last``. On ``mission.return`` it leaves the route and flies straight home
    at the speed the message gives, and the episode ends when it is there.

    ``protocol = "paper"``: the 2023 AirSim loop (:class:`PaperFlight`): stop-and-go legs,
    a hover requested by ``mission.hover`` is served at the next waypoint reached, and
    the episode ends when the UAV leaves waypoint ``last_waypoint``; the end message
    carries the mission clock, which starts ``takeoff_s`` before the first move.
    """

    subscribe = [HOVER, RETURN_HOME]
    optional = (HOVER, RETURN_HOME)  # (a mission that holds the UAV or sends it home, when there is one)
    publishes = (POSITIONS, FORECAST, caviar.END_TOPIC)

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
        protocol: str = "physical"
        """``physical`` or ``paper`` (see the class docstring and docs/paper-protocol.md)."""
        last_waypoint: int = paper.PAPER_LAST_WAYPOINT
        """paper: the episode ends when the UAV leaves this waypoint (0-based row)."""
        takeoff_s: float = paper.PAPER_TAKEOFF_S
        """paper: mission clock when the UAV first leaves waypoint 0 (takeoff, an estimate)."""
        acceleration: float = paper.PAPER_ACCELERATION
        """paper: m/s² of the stop-and-go legs."""
        forecast_steps: int = 0
        """Also publish ``3D.mobility.forecast``: the positions of the next this many
        steps, as the flight will compute them if no hover request arrives (for the
        look-ahead ray tracing of sionna-link). 0: no forecast (the default)."""

        def __post_init__(self):
            paper.check_protocol(self.protocol)
            if self.frame not in ("airsim_ned", "scene"):
                raise ValueError(f"frame: expected 'airsim_ned' or 'scene', got {self.frame!r}")
            if not self.speed > 0:
                raise ValueError(f"speed: expected a positive number of m/s, got {self.speed}")
            if not self.acceleration > 0 or self.takeoff_s < 0 or self.last_waypoint < 1:
                raise ValueError("acceleration must be > 0, takeoff_s >= 0 and last_waypoint >= 1")
            if self.forecast_steps < 0:
                raise ValueError(f"forecast_steps: expected >= 0, got {self.forecast_steps}")

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
        self.speed = p.speed
        self.home: dict | None = None  # {"reason"} once it flies home
        self.hover_until = -1.0
        self.ts = ctx.ts
        self.paper: PaperFlight | None = None
        if p.protocol == "paper":
            if p.last_waypoint >= len(pts):
                raise ValueError(f"last_waypoint = {p.last_waypoint}: the route has {len(pts)} waypoints")
            self.paper = PaperFlight(pts, ctx.ts, p.speed, p.acceleration, p.last_waypoint)

    def step(self, t, inbox):
        if self.paper is not None:
            yield from self._paper_step(self.paper, t, inbox)
            return
        for m in inbox.on(HOVER):
            if m.data.get("UE_Id") == self.p.ue_id and self.home is None:
                self.hover_until = max(self.hover_until, t + float(m.data["seconds"]))
        for m in inbox.on(RETURN_HOME):
            if m.data.get("UE_Id") == self.p.ue_id and self.home is None:
                self._fly_home(m.data)
        yield POSITIONS, position_payload(self.p.ue_id, self.path.at(self.s))
        if self.p.forecast_steps:
            # The same additions the next steps will make (bit-identical positions),
            # holding while a hover already requested lasts.
            s, ahead = self.s, []
            for k in range(self.p.forecast_steps):
                if t + k * self.ts + 1e-9 >= self.hover_until:
                    s += self.speed * self.ts
                ahead.append(self.path.at(s))
            yield FORECAST, forecast_payload(self.p.ue_id, ahead, self.ts)
        if self.s >= self.path.length and self.home is not None:
            yield caviar.END_TOPIC, {"reason": f"{self.p.ue_id} flew home: {self.home['reason']}"}
        elif self.s >= self.path.length and self.p.end_at_last:
            yield caviar.END_TOPIC, {"reason": f"{self.p.ue_id} reached its last waypoint"}
        if t + 1e-9 >= self.hover_until:
            self.s += self.speed * self.ts

    def _fly_home(self, command: dict) -> None:
        """Leaves the route: a straight path from where the UAV is to ``command["home"]``
        (the route's first waypoint where the command names none), at its speed."""
        here = self.path.at(self.s)
        home = np.asarray(command.get("home") or self.path.points[0], dtype=float)
        self.path = Path(np.stack([here, home]))
        self.s, self.hover_until = 0.0, -1.0
        self.speed = float(command.get("speed_mps") or self.p.speed)
        self.home = {"reason": str(command.get("reason", "sent home"))}

    def state(self):
        # The route and parameters come from setup; what moves is here (and the way home).
        return {"s": self.s, "hover_until": self.hover_until, "paper": copy.deepcopy(self.paper),
                "speed": self.speed, "home": self.home,
                "home_path": self.path.points.tolist() if self.home is not None else None}

    def restore(self, state):
        self.s, self.hover_until, self.paper = state["s"], state["hover_until"], state["paper"]
        self.speed, self.home = state.get("speed", self.p.speed), state.get("home")
        if state.get("home_path") is not None:
            self.path = Path(np.array(state["home_path"]))

    def _paper_step(self, f: PaperFlight, t, inbox):
        for m in inbox.on(HOVER):
            if m.data.get("UE_Id") == self.p.ue_id:
                f.request_hover(float(m.data["seconds"]))
        if f.k > 0:
            # The waypoint logic of the previous step, which sees that step's detections
            # (the mission runs after mobility): the order of the 2023 loop.
            if f.decide():
                time_s = (f.k - 1) * self.ts
                yield caviar.END_TOPIC, {
                    "reason": f"{self.p.ue_id} left waypoint {self.p.last_waypoint}",
                    "mission_time_s": self.p.takeoff_s + time_s, "clock_offset_s": self.p.takeoff_s,
                    "flight_time_s": time_s, "hover_s": f.hover_steps * self.ts,
                    "flown_m": f.flown_m}
                return
            f.advance()
        f.k += 1
        yield POSITIONS, position_payload(self.p.ue_id, f.pos)
        if self.p.forecast_steps:
            # The flight's own logic run ahead on a copy, with no new hover requests.
            g, ahead = copy.deepcopy(f), []
            for _ in range(self.p.forecast_steps):
                if g.decide():
                    break
                g.advance()
                ahead.append(g.pos.copy())
            yield FORECAST, forecast_payload(self.p.ue_id, ahead, self.ts)


def forecast_payload(ue_id: str, positions, ts: float, ue_type: str = "UAV") -> dict:
    """A ``3D.mobility.forecast`` payload: the positions of the next steps."""
    return {"UE_type": ue_type, "UE_Id": ue_id, "ts": float(ts),
            "positions": [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in positions]}


class PaperFlight:
    """The flight of the 2023 AirSim loop, stepped every ``ts``.

    Each step: the position is published; then (waypoint logic) if the UAV is within
    0.5 m (x, y) and 0.6 m (z) of its target waypoint: a pending hover starts a
    countdown of ceil(S / ts) steps; with none pending it moves on to the next waypoint,
    and leaving ``last`` ends the flight. During a countdown, requests overwrite the
    pending S but the end of the countdown clears it (so they are lost); a request in
    the step after the countdown starts a new one. A hover holds the UAV for
    (ceil(S / ts) + 1) · ts. Legs are straight, at ``speed`` with ``acceleration`` at
    both ends (AirSim's ``moveToPositionAsync`` stops at every waypoint).
    """

    def __init__(self, points, ts: float, speed: float, acceleration: float, last: int):
        self.points = np.asarray(points, dtype=float)
        self.ts, self.speed, self.acc, self.last = ts, speed, acceleration, last
        self.pos = self.points[0].copy()
        self.target = 0
        self.leg_start = self.pos.copy()
        self.leg_tau = 0.0
        self.pending: float | None = None
        self.countdown = 0
        self.hover_steps = 0
        self.flown_m = 0.0
        self.k = 0  # steps published

    def request_hover(self, seconds: float) -> None:
        self.pending = seconds  # the last request wins

    def arrived(self) -> bool:
        d = np.abs(self.pos - self.points[self.target])
        return bool(np.all(d <= np.asarray(paper.PAPER_ARRIVAL_TOLERANCE)))

    def decide(self) -> bool:
        """The waypoint logic; True when the UAV leaves the last waypoint (the end)."""
        if not self.arrived():
            return False
        if self.countdown == 0 and self.pending is not None:
            self.countdown = max(1, math.ceil(self.pending / self.ts - 1e-9))
            self.hover_steps += 1
        elif self.countdown == 0:
            if self.target == self.last:
                return True
            self.target += 1
            self.leg_start, self.leg_tau = self.pos.copy(), 0.0
        else:
            self.hover_steps += 1
            self.countdown -= 1
            if self.countdown == 0:
                self.pending = None
        return False

    def advance(self) -> None:
        """Moves along the current leg for one step (stays put once at its end)."""
        goal = self.points[self.target]
        vec = goal - self.leg_start
        length = float(np.linalg.norm(vec))
        if length == 0:
            return
        self.leg_tau += self.ts
        s = leg_distance(length, self.leg_tau, self.speed, self.acc)
        new = self.leg_start + vec * (s / length)
        self.flown_m += float(np.linalg.norm(new - self.pos))
        self.pos = new


def leg_distance(length: float, tau: float, speed: float, acc: float) -> float:
    """Distance covered ``tau`` seconds after leaving on a straight leg of ``length``
    metres: accelerate at ``acc`` up to ``speed``, cruise, decelerate to stop at the end."""
    t_acc = speed / acc
    if length < speed * t_acc:  # triangular profile: never reaches the cruise speed
        t_half = math.sqrt(length / acc)
        if tau <= t_half:
            return 0.5 * acc * tau**2
        rest = max(2 * t_half - tau, 0.0)
        return length - 0.5 * acc * rest**2
    total = length / speed + t_acc
    if tau <= t_acc:
        return 0.5 * acc * tau**2
    if tau <= total - t_acc:
        return 0.5 * speed * t_acc + speed * (tau - t_acc)
    rest = max(total - tau, 0.0)
    return length - 0.5 * acc * rest**2
