"""The propulsion power of a rotary-wing UAV: Zeng, Xu and Zhang, "Energy Minimization for
Wireless Communication with Rotary-Wing UAV", IEEE Trans. Wireless Commun. 18(4), 2019,
eq. (12) and Table I, with climb and acceleration terms added.

In level flight at speed V (m/s)::

    P(V) = P0 (1 + 3V²/U_tip²)                                   blade profile
         + Pi (√(1 + V⁴/(4 v0⁴)) − V²/(2 v0²))^½                 induced
         + ½ d0 ρ s A V³                                          parasite (fuselage drag)

    P0 = δ/8 ρ s A Ω³ R³,  Pi = (1 + k) W^{3/2} / √(2ρA),  v0 = √(W / (2ρA))

so that hovering costs P0 + Pi (168.49 W with Table I's values). Its minimum is the
maximum-endurance speed V_me, and the minimum of P(V)/V (energy per metre) the
maximum-range speed V_mr (10.2 and 18.3 m/s in the paper's Fig. 3).

Climbing and speeding up cost what energy conservation says (as the paper's energy
model, and Zeng & Zhang 2017's for fixed wings, account for them): W·v_z to climb at
v_z, and m·a·v to accelerate, m = W/g. A multirotor does not recharge while it descends
or slows down: those terms count only where they are positive.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

GRAVITY = 9.80665  # m/s²
AIR_DENSITY = (0.1, 2.0)
"""kg/m³ an airframe may fly in: from about 15 km up to cold air below sea level."""


def _positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a positive number, got {value!r}")


@dataclasses.dataclass(frozen=True)
class RotaryWing:
    """A rotary-wing UAV's airframe and rotor; the defaults are Zeng et al.'s Table I."""

    weight_n: float = 20.0
    """W: aircraft weight (N)."""
    air_density: float = 1.225
    """ρ (kg/m³)."""
    rotor_radius_m: float = 0.4
    """R."""
    rotor_area_m2: float = 0.503
    """A: rotor disc area (m²), πR²."""
    blade_angular_velocity: float = 300.0
    """Ω (rad/s); the tip speed U_tip = ΩR is 120 m/s."""
    rotor_solidity: float = 0.05
    """s = b·c/(πR): blade area over disc area (4 blades of 0.0157 m chord)."""
    fuselage_drag_ratio: float = 0.6
    """d0 = S_FP/(s·A), S_FP = 0.0151 m² the fuselage's equivalent flat plate area."""
    induced_power_correction: float = 0.1
    """k: incremental correction factor to the induced power."""
    profile_drag_coefficient: float = 0.012
    """δ."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            _positive(f.name, getattr(self, f.name))
        if self.rotor_solidity >= 1:
            raise ValueError(f"rotor_solidity: expected a share of the disc in (0, 1), got {self.rotor_solidity!r}")
        if not AIR_DENSITY[0] <= self.air_density <= AIR_DENSITY[1]:
            raise ValueError(f"air_density: expected kg/m³ of air in [{AIR_DENSITY[0]}, {AIR_DENSITY[1]}] "
                             f"(1.225 at sea level, 0.41 at 10 km), got {self.air_density!r}")
        try:  # (the model's powers, finite for this airframe: no overflow in set-up or a step)
            finite = all(math.isfinite(p) for p in (self.hover_power_w, float(self.level_power_w(self.tip_speed)),
                                                     self.induced_velocity))
        except (OverflowError, ZeroDivisionError, ValueError):
            finite = False
        if not finite:
            raise ValueError("weight_n: this airframe's hover and flight powers overflow (they are not finite "
                             "numbers); check weight_n, rotor_radius_m, rotor_area_m2 and blade_angular_velocity")

    @property
    def tip_speed(self) -> float:
        """U_tip = ΩR (m/s)."""
        return self.blade_angular_velocity * self.rotor_radius_m

    @property
    def blade_profile_power_w(self) -> float:
        """P0 = δ/8 ρ s A Ω³ R³: the blade profile power in hover."""
        return (self.profile_drag_coefficient / 8 * self.air_density * self.rotor_solidity * self.rotor_area_m2
                * self.blade_angular_velocity ** 3 * self.rotor_radius_m ** 3)

    @property
    def induced_power_w(self) -> float:
        """Pi = (1 + k) W^{3/2} / √(2ρA): the induced power in hover."""
        return ((1 + self.induced_power_correction) * self.weight_n ** 1.5
                / math.sqrt(2 * self.air_density * self.rotor_area_m2))

    @property
    def induced_velocity(self) -> float:
        """v0 = √(W / (2ρA)): the mean rotor induced velocity in hover (m/s)."""
        return math.sqrt(self.weight_n / (2 * self.air_density * self.rotor_area_m2))

    @property
    def mass_kg(self) -> float:
        return self.weight_n / GRAVITY

    @property
    def hover_power_w(self) -> float:
        """P0 + Pi."""
        return self.blade_profile_power_w + self.induced_power_w

    def level_power_w(self, speed):
        """P(V) of level flight at ``speed`` (m/s; a number or an array)."""
        v = np.asarray(speed, dtype=float)
        v0 = self.induced_velocity
        blade = self.blade_profile_power_w * (1 + 3 * v ** 2 / self.tip_speed ** 2)
        induced = self.induced_power_w * np.sqrt(np.sqrt(1 + v ** 4 / (4 * v0 ** 4)) - v ** 2 / (2 * v0 ** 2))
        parasite = 0.5 * self.fuselage_drag_ratio * self.air_density * self.rotor_solidity * self.rotor_area_m2 * v ** 3
        out = blade + induced + parasite
        return float(out) if out.ndim == 0 else out

    def power_w(self, velocity, acceleration=(0.0, 0.0, 0.0)) -> float:
        """The propulsion power at ``velocity`` (3, m/s) while accelerating at
        ``acceleration`` (3, m/s²): P(horizontal speed) + W·v_z + m·a·v, the last two
        where they are positive."""
        v = np.asarray(velocity, dtype=float)
        a = np.asarray(acceleration, dtype=float)
        climb = self.weight_n * max(float(v[2]), 0.0)
        kinetic = self.mass_kg * max(float(a @ v), 0.0)
        return float(self.level_power_w(math.hypot(v[0], v[1]))) + climb + kinetic

    def step_power_w(self, previous_velocity, velocity, dt: float) -> float:
        """The mean propulsion power over a step of ``dt`` seconds that ends at ``velocity``
        (3, m/s) and began at ``previous_velocity``: P(horizontal speed) + W·v_z plus the
        change of kinetic energy over ``dt``, ½m(|v|² − |v_prev|²)/dt (m·a·v̄ at the
        step's mean velocity: exact for a constant acceleration), where positive."""
        v, v_prev = np.asarray(velocity, dtype=float), np.asarray(previous_velocity, dtype=float)
        _positive("dt", dt)
        kinetic = 0.5 * self.mass_kg * (float(v @ v) - float(v_prev @ v_prev)) / dt
        return self.power_w(v) + max(kinetic, 0.0)

    def max_endurance_speed(self) -> float:
        """V_me: the speed of least power (the longest flight on a battery), found numerically."""
        return _argmin(self.level_power_w, 1e-3, 4 * self.tip_speed / 3)

    def max_range_speed(self) -> float:
        """V_mr: the speed of least energy per metre, P(V)/V (the farthest flight)."""
        return _argmin(lambda v: self.level_power_w(v) / v, 0.5, 4 * self.tip_speed / 3)

    def energy_per_metre_j(self, speed: float) -> float:
        """P(V)/V (J/m) in level flight at ``speed``."""
        _positive("speed", speed)
        return float(self.level_power_w(speed)) / speed


def _argmin(f, lo: float, hi: float) -> float:
    from scipy.optimize import minimize_scalar

    return float(minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6}).x)


@dataclasses.dataclass(frozen=True)
class Battery:
    """A UAV's battery and what it feeds besides the rotors."""

    capacity_wh: float = 100.0
    """Usable energy when full (Wh)."""
    initial_soc: float = 1.0
    """State of charge at the start, a share of ``capacity_wh``."""
    reserve: float = 0.2
    """The share a mission keeps to land with: it sends a UAV home before the battery
    holds less than the way back plus this."""

    def __post_init__(self):
        _positive("capacity_wh", self.capacity_wh)
        if not (isinstance(self.initial_soc, (int, float)) and 0 < self.initial_soc <= 1):
            raise ValueError(f"initial_soc: expected a share in (0, 1], got {self.initial_soc!r}")
        if not (isinstance(self.reserve, (int, float)) and 0 <= self.reserve < self.initial_soc):
            raise ValueError(f"reserve: expected a share in [0, initial_soc = {self.initial_soc}), "
                             f"got {self.reserve!r}")
