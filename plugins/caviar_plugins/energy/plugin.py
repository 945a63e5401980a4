"""``uav-energy``: every UAV's power, energy and battery, step by step, from where it flies.

From each UAV's positions it takes the velocity over the last step (and the acceleration
from the step before) and charges the battery the step's energy::

    E_step = (P_propulsion(v, a) + P_communication + P_computing) · Δt

with the rotary-wing propulsion model of :class:`~caviar_plugins.energy.rotary_wing.RotaryWing`
(Zeng, Xu and Zhang 2019, with climb and acceleration). It publishes ``uav.energy`` per UAV
and step, and the energy to fly home from where the UAV is (straight, at the airframe's
maximum-range speed unless ``return_speed_mps`` says otherwise, climbing where home is
higher). ``must_return`` turns true, and stays true, at the last step at which a command
still brings the UAV home with its ``battery.reserve`` (a command takes effect at the next
step; the next step's command would come too late): a mission then sends the UAV home
(``mission.return``) and it lands with its reserve. A UAV whose battery runs out ends the
episode.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np

import caviar
from caviar_plugins.energy.rotary_wing import Battery, RotaryWing
from caviar_plugins.schema import ENERGY, POSITIONS, UE_TYPES, VIEW_ENERGY, read_position

WH = 3600.0  # J


class UavEnergy(caviar.Plugin):
    subscribe = [POSITIONS]
    publishes = (ENERGY, VIEW_ENERGY, caviar.END_TOPIC)

    @dataclasses.dataclass
    class Params:
        airframe: RotaryWing = dataclasses.field(default_factory=RotaryWing)
        """The rotary-wing airframe (Zeng et al. 2019, Table I by default): ``weight_n``,
        ``rotor_radius_m``, ``blade_angular_velocity``... (see
        :class:`~caviar_plugins.energy.rotary_wing.RotaryWing`)."""
        battery: Battery = dataclasses.field(default_factory=Battery)
        """``capacity_wh``, ``initial_soc``, ``reserve`` (see
        :class:`~caviar_plugins.energy.rotary_wing.Battery`)."""
        communication_w: float = 5.0
        """The radio's power draw (W): its transmit power over the amplifier's efficiency and
        its circuits."""
        computing_w: float = 10.0
        """The on-board computer's power draw (W), e.g. an embedded GPU running the camera
        and the detector."""
        ue_types: list[str] = dataclasses.field(default_factory=lambda: ["UAV"])
        """Which UEs carry a battery (``UE_type`` of their positions)."""
        home: list[float] | None = None
        """Where the UAVs land ([x, y, z], scene frame); None: where each was first seen."""
        return_speed_mps: float | None = None
        """The speed of the way home; None: the airframe's maximum-range speed (the least
        energy per metre)."""

        def __post_init__(self):
            for key in ("communication_w", "computing_w"):
                v = getattr(self, key)
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                    raise ValueError(f"{key}: expected a power >= 0 in W, got {v!r}")
            if self.home is not None and (len(self.home) != 3 or not all(math.isfinite(v) for v in self.home)):
                raise ValueError(f"home: expected [x, y, z] in metres, got {self.home!r}")
            if self.return_speed_mps is not None and not (
                    isinstance(self.return_speed_mps, (int, float)) and 0 < self.return_speed_mps < 100):
                raise ValueError(f"return_speed_mps: expected a speed in (0, 100) m/s, got {self.return_speed_mps!r}")
            if not self.ue_types:
                raise ValueError("ue_types: expected at least one UE type")
            unknown = [t for t in self.ue_types if t not in UE_TYPES]
            if unknown:
                warnings.warn(caviar.ConfigWarning(
                    f"no shipped module publishes UEs of type {', '.join(map(repr, unknown))} (they publish "
                    f"{', '.join(UE_TYPES)}); unless a module of yours does, no UE of that type carries a battery",
                    "ue_types"), stacklevel=2)

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.p = p
        self.return_speed = p.return_speed_mps or p.airframe.max_range_speed()
        # Per UAV: home, last time, position and velocity, energy used (Wh), latched decision.
        self.uavs: dict[str, dict[str, Any]] = {}

    def state(self):
        return {"uavs": self.uavs}

    def restore(self, state):
        self.uavs = state["uavs"]

    def return_wh(self, position: np.ndarray, home: np.ndarray, step_s: float | None = None) -> float:
        """The energy (Wh) to fly straight from ``position`` to ``home`` at the return speed:
        getting up to that speed (½mV², from a stop), the flight and any climb; with
        ``step_s``, the flight in whole steps (its last, shorter one costs a whole step)."""
        p, v = self.p, self.return_speed
        seconds = math.dist(position, home) / v  # (the flight flies the straight 3D line home)
        if step_s:
            seconds = math.ceil(seconds / step_s - 1e-9) * step_s
        if seconds == 0:
            return 0.0
        flying = seconds * (p.airframe.level_power_w(v) + p.communication_w + p.computing_w)
        climb = p.airframe.weight_n * max(float(home[2] - position[2]), 0.0)
        return (0.5 * p.airframe.mass_kg * v ** 2 + flying + climb) / WH

    def step(self, t, inbox):
        labels = []
        for message in self._step(t, inbox):
            yield message
            topic, e = message
            if topic == ENERGY:  # the browser view: the state of charge beside the UAV
                x, y, z = self.uavs[e["UE_Id"]]["position"]
                colour = "#66bb6a" if e["soc"] > 0.5 else "#ffca28" if e["soc"] > e["reserve_wh"] / e["capacity_wh"] \
                    else "#ef5350"
                text = f"{e['UE_Id']} {100 * e['soc']:.0f} %" + (" → home" if e["must_return"] else "")
                labels.append({"x": x, "y": y, "z": z + 3.0, "color": colour, "text": text})
        if labels:
            yield VIEW_ENERGY, {"labels": labels}

    def _step(self, t, inbox):
        p = self.p
        capacity = p.battery.capacity_wh
        for m in inbox.on(POSITIONS):
            if m.data.get("UE_type") not in p.ue_types:
                continue
            ue, pos = m.data["UE_Id"], read_position(m.data)
            u = self.uavs.get(ue)
            if u is None:  # first seen: on the ground at home, nothing used yet
                home = p.home if p.home is not None else pos.tolist()
                u = self.uavs[ue] = {"home": [float(v) for v in home], "time": t, "position": pos.tolist(),
                                     "velocity": [0.0, 0.0, 0.0], "energy_wh": 0.0, "must_return": False,
                                     "depleted": False}
                velocity, propulsion, dt = np.zeros(3), 0.0, 0.0
            else:
                dt = t - u["time"]
                if dt <= 0:
                    continue
                velocity = (pos - np.array(u["position"])) / dt
                propulsion = p.airframe.step_power_w(u["velocity"], velocity, dt)
            power = propulsion + p.communication_w + p.computing_w
            u["energy_wh"] += power * dt / WH
            u.update(time=t, position=pos.tolist(), velocity=velocity.tolist())
            remaining = p.battery.initial_soc * capacity - u["energy_wh"]
            reserve = p.battery.reserve * capacity
            home_wh = self.return_wh(pos, np.array(u["home"]))
            # Return now if waiting would be too late: a command sent at the next step turns the
            # UAV a step after that (the flight reads it at the following step). Budget those
            # two steps, and the way home from where the UAV would be then, in whole steps.
            ahead = self.ctx.ts * self.ctx.every
            step_wh = max(power, p.airframe.hover_power_w) * ahead / WH
            later_wh = self.return_wh(pos + velocity * 2 * ahead, np.array(u["home"]), step_s=ahead)
            u["must_return"] = u["must_return"] or remaining - reserve - 2 * step_wh <= max(home_wh, later_wh)
            yield ENERGY, {"UE_type": m.data["UE_type"], "UE_Id": ue,
                           "speed_mps": round(float(np.linalg.norm(velocity)), 4),
                           "power_w": round(power, 3), "propulsion_w": round(propulsion, 3),
                           "energy_wh": round(u["energy_wh"], 5), "remaining_wh": round(max(remaining, 0.0), 5),
                           "soc": round(max(remaining, 0.0) / capacity, 6), "capacity_wh": capacity,
                           "reserve_wh": round(reserve, 4),
                           "home": u["home"], "return_wh": round(home_wh, 5),
                           "return_speed_mps": round(self.return_speed, 4), "must_return": u["must_return"]}
            if remaining <= 0 and not u["depleted"]:
                u["depleted"] = True
                yield caviar.END_TOPIC, {"reason": f"{ue}'s battery ran out at t = {t:g} s "
                                                   f"({u['energy_wh']:.2f} Wh used of {capacity:g} Wh)"}
