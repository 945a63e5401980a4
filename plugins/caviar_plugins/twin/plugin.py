"""The self-calibrating twin's modules:

* ``scene-fitter`` (:class:`SceneFitter`): collects the measurements vehicles report on
  ``measurements.*`` while the run goes, predicts each new one with the twin's current
  materials before it learns from it (the twin's prediction error, on ``twin.fit``), and every
  ``refit_s`` of virtual time refits the materials (:func:`~caviar_plugins.twin.fit.fit_materials`,
  warm-started from the last fit) and publishes them on ``twin.materials``, which the
  ray-traced links (``sionna-link``) apply from then on;
* ``measurement-emulator`` (:class:`MeasurementEmulator`): **a stand-in for a physical
  vehicle's radio measurements**, for experiments without one: it ray traces each UAV's
  position in the same scene with hidden "true" materials and reports the received power with
  measurement noise on ``measurements.<UE_Id>``.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np

import caviar
from caviar_plugins.rt.materials import PROPERTIES, apply_materials, scene_materials, used_materials
from caviar_plugins.rt.received_power import ReceivedPower
from caviar_plugins.rt.scene import build_scene
from caviar_plugins.rt.settings import TraceSettings
from caviar_plugins.schema import MATERIALS, POSITIONS, TWIN_FIT, read_position
from caviar_plugins.twin.fit import FIT_RAYS, FitSettings, fit_materials, rmse
from caviar_plugins.twin.measurements import TOPIC, MeasurementError, Measurements, from_messages

MAX_SAMPLES = 5000
"""Samples a refit traces at most (the oldest beyond it are dropped): one receiver each."""


def _check_materials(table: Any, key: str) -> dict[str, dict[str, float]]:
    if not isinstance(table, dict):
        raise ValueError(f"{key}: expected a table {{material = {{property = value}}}}, got {table!r}")
    for name, props in table.items():
        if not isinstance(props, dict):
            raise ValueError(f"{key}.{name}: expected a table {{property = value}}, got {props!r}")
        for prop, v in props.items():
            if prop not in (*PROPERTIES, "thickness"):
                raise ValueError(f"{key}.{name}.{prop}: not a material property (expected one of "
                                 f"{', '.join((*PROPERTIES, 'thickness'))})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0 or (
                    prop == "relative_permittivity" and v < 1) or (prop == "scattering_coefficient" and v > 1):
                raise ValueError(f"{key}.{name}.{prop}: expected a physical value (ε_r >= 1, σ >= 0, "
                                 f"0 <= S <= 1, thickness >= 0), got {v!r}")
    return table


@dataclasses.dataclass
class SceneFitterParams:
    scene: str
    """The twin's scene (a shipped name or a Mitsuba XML file), as its ray-traced links load it."""
    refit_s: float = 10.0
    """Virtual seconds between refits."""
    min_samples: int = 10
    """Samples needed before the first refit."""
    iterations: int = 10
    """Descent iterations per refit (each starts from the last fit's values)."""
    learn: list[str] = dataclasses.field(default_factory=lambda: ["relative_permittivity"])
    """The properties learned per material (``relative_permittivity``, ``conductivity``,
    ``scattering_coefficient``)."""
    materials: list[str] = dataclasses.field(default_factory=list)
    """The materials learned (empty: every material the scene's objects use)."""
    method: str = "lm"
    """The descent: ``"lm"`` (Levenberg–Marquardt) or ``"adam"``
    (:class:`~caviar_plugins.twin.fit.FitSettings`)."""
    learning_rate: float = 0.02
    """With ``method = "adam"``: Adam's step in the properties' logs."""
    holdout: float = 0.2
    """The share of the samples each refit holds out to judge itself (``twin.fit``'s
    ``rmse_db.held_out``)."""
    noise_db: float = 1.0
    """The measurements' noise (dB): the identifiability bound."""
    max_log_std: float = 0.2
    """A property is learned only if the data bound its log within this (Cramér–Rao)."""
    max_samples: int = 1000
    """The most recent samples a refit uses (at most :data:`MAX_SAMPLES`)."""
    search_points: int = 160
    """A refit searches each property over this many values before it descends
    (:func:`~caviar_plugins.twin.fit.coarse_search`) when the samples have at least doubled
    since the last search (the first refit always); the others descend from the last values."""
    restarts: int = 4
    """A searching refit then starts this many more rounds from random values
    (:attr:`~caviar_plugins.twin.fit.FitSettings.restarts`), and as many descents from the
    rival values its search found (:attr:`~caviar_plugins.twin.fit.FitSettings.rival_starts`)."""
    raytracing: TraceSettings = dataclasses.field(default_factory=lambda: FIT_RAYS)

    def __post_init__(self):
        if not (isinstance(self.refit_s, (int, float)) and np.isfinite(self.refit_s) and self.refit_s > 0):
            raise ValueError(f"refit_s: expected a number of seconds > 0, got {self.refit_s!r}")
        for key in ("min_samples", "max_samples"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_SAMPLES:
                raise ValueError(f"{key}: expected a whole number from 1 to {MAX_SAMPLES}, got {v!r}")
        self.fit = FitSettings(learn=tuple(self.learn), materials=tuple(self.materials), holdout=self.holdout,
                               iterations=self.iterations, method=self.method,
                               learning_rate=self.learning_rate,
                               noise_db=self.noise_db, max_log_std=self.max_log_std, patience=self.iterations,
                               search_points=self.search_points, search_sweeps=2,
                               restarts=self.restarts, rival_starts=self.restarts)


class SceneFitter(caviar.Plugin):
    subscribe = [f"{TOPIC}.*"]
    publishes = (MATERIALS, TWIN_FIT)
    Params = SceneFitterParams

    def setup(self, ctx):
        p = ctx.params
        self.p = p
        self.seed = ctx.seed
        self.scene = build_scene(p.scene, ctx.config_dir, threads=p.raytracing.threads)
        unknown = sorted(set(p.materials) - set(used_materials(self.scene)))
        if unknown:
            raise caviar.ConfigError(f"'{unknown[0]}' is not a material an object of {p.scene} uses "
                                     f"({', '.join(used_materials(self.scene))})", "params.materials")
        self.predictor: ReceivedPower | None = None
        self.samples: list[dict[str, float]] = []
        self.last_refit = None
        self.refits = 0
        self.searched_with = 0
        """The samples the last refit that searched had."""
        self.carrier: tuple[float, float] | None = None
        self.rejected = 0
        """Measurements dropped for a bad field (each warned about)."""

    def _predict(self, data: Measurements) -> np.ndarray:
        if self.predictor is None:
            self.scene.frequency = data.frequency_hz
            self.predictor = ReceivedPower(self.scene, self.p.raytracing, seed=self.seed)
        sites, index = data.transmitters()
        self.predictor.place(data.rx, sites)
        return self.predictor.predict(np.stack([np.arange(len(data)), index], axis=1), data.tx_power_dbm)

    def step(self, t, inbox):
        good = []
        for m in inbox.on(f"{TOPIC}.*"):
            try:
                one = from_messages([m])
                carrier = (one.frequency_hz, one.bandwidth_hz)
                if self.carrier is not None and carrier != self.carrier:
                    raise MeasurementError(f"topic {m.topic}: carrier {carrier[0]:g} Hz, bandwidth {carrier[1]:g} Hz; "
                                           f"this fit's are {self.carrier[0]:g} Hz, {self.carrier[1]:g} Hz")
                self.carrier = carrier
                good.append(one)
            except MeasurementError as e:  # a bad report is dropped, said and counted, not fatal
                self.rejected += 1
                warnings.warn(f"scene-fitter: dropped a measurement: {e}", RuntimeWarning, stacklevel=2)
        if good:
            new = Measurements.join(good)
            pred = self._predict(new)
            err = rmse(pred, new.power_dbm, np.ones(len(new), dtype=bool))
            self.samples += new.rows()
            self.samples = self.samples[-self.p.max_samples:]
            yield TWIN_FIT, {"time": t, "samples": len(self.samples), "new": len(new), "rejected": self.rejected,
                             "prediction_error_db": None if np.isnan(err) else round(err, 4)}
        due = self.last_refit is None or t - self.last_refit >= self.p.refit_s - 1e-9
        if due and len(self.samples) >= self.p.min_samples:
            self.last_refit = t
            yield from self._refit(t)

    def _refit(self, t: float):
        data = from_messages([_Sample(s) for s in self.samples])
        search = len(data) >= 2 * self.searched_with
        fit = self.p.fit if search else dataclasses.replace(self.p.fit, search_sweeps=0, restarts=0, rival_starts=0)
        if search:
            self.searched_with = len(data)
        result = fit_materials(self.scene, data, fit, self.p.raytracing, run_seed=self.seed)
        self.refits += 1
        merged: dict[str, dict[str, float]] = {}
        for (m, p), v in result.learned.items():
            merged.setdefault(m, {})[p] = round(v, 6)
        yield MATERIALS, {"time": t, "materials": merged}
        yield TWIN_FIT, {"time": t, "samples": len(data), "refit": self.refits, "rmse_db": result.rmse_db,
                          "learned": {f"{m}.{p}": v for (m, p), v in result.learned.items()},
                          "not_identifiable": [f"{m}.{p}" for (m, p) in result.start
                                               if (m, p) not in result.identifiability.identifiable],
                          "confounded": {f"{m}.{p}": [f"{a}.{b}" for a, b in fixed]
                                         for (m, p), fixed in result.identifiability.confounded.items()},
                          "ambiguous": {f"{m}.{p}": [round(v, 4) for v in values]
                                        for (m, p), values in result.identifiability.ambiguous.items()},
                          **({"delay_spread_ns": result.delay_spread_ns} if result.delay_spread_ns else {})}
        self.predictor = None  # the fit placed its own receivers

    def state(self):
        return {"samples": self.samples, "last_refit": self.last_refit, "refits": self.refits,
                "rejected": self.rejected, "carrier": self.carrier, "searched_with": self.searched_with,
                "materials": {k: v.as_dict() for k, v in scene_materials(self.scene).items()}}

    def restore(self, state):
        self.samples, self.last_refit, self.refits = state["samples"], state["last_refit"], state["refits"]
        self.rejected = state["rejected"]
        self.carrier, self.searched_with = state["carrier"], state["searched_with"]
        apply_materials(self.scene, state["materials"])


class _Sample:
    """A stored sample as a message (what :func:`from_messages` reads)."""

    topic, step = f"{TOPIC}.stored", None

    def __init__(self, data):
        self.data = data


@dataclasses.dataclass
class MeasurementEmulatorParams:
    scene: str
    tx_position: list[float]
    """The measured transmitter (m, scene frame)."""
    truth: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    """The hidden "true" materials: ``{material = {property = value}}`` on top of the scene's."""
    noise_db: float = 1.0
    """Measurement noise (dB, one standard deviation, Gaussian)."""
    tx_power_dbm: float = 30.0
    frequency_hz: float = 3.5e9
    bandwidth_hz: float = 20e6
    raytracing: TraceSettings = dataclasses.field(default_factory=lambda: FIT_RAYS)
    profiles: bool = False
    """Also report each sample's power-delay profile (``pdp_delay_s``, ``pdp_power_dbm``): the
    paths binned at 1/``bandwidth_hz``, each tap with ``noise_db`` of noise of its own."""

    def __post_init__(self):
        _check_materials(self.truth, "truth")
        if not isinstance(self.profiles, bool):
            raise ValueError(f"profiles: expected true or false, got {self.profiles!r}")
        if len(self.tx_position) != 3:
            raise ValueError(f"tx_position: expected [x, y, z] (m), got {self.tx_position!r}")
        if not (isinstance(self.noise_db, (int, float)) and 0 <= self.noise_db < 30):
            raise ValueError(f"noise_db: expected a standard deviation in [0, 30) dB, got {self.noise_db!r}")
        for key in ("frequency_hz", "bandwidth_hz"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{key}: expected a number > 0 (Hz), got {v!r}")


class MeasurementEmulator(caviar.Plugin):
    """A stand-in for a vehicle's radio measurements (see the module's docstring)."""

    subscribe = [POSITIONS]
    publishes = (f"{TOPIC}.*",)
    Params = MeasurementEmulatorParams

    def setup(self, ctx):
        p = ctx.params
        self.p = p
        scene = build_scene(p.scene, ctx.config_dir, frequency_hz=p.frequency_hz, threads=p.raytracing.threads)
        try:
            apply_materials(scene, p.truth)
        except KeyError as e:
            raise caviar.ConfigError(str(e.args[0]), "params.truth") from None
        self.model = ReceivedPower(scene, p.raytracing, seed=ctx.seed)
        self.rng = np.random.default_rng(ctx.seed)

    def step(self, t, inbox):
        positions = {m.data["UE_Id"]: read_position(m.data) for m in inbox.on(POSITIONS)}
        if not positions:
            return
        ues = sorted(positions)
        self.model.place(np.array([positions[u] for u in ues]), np.array([self.p.tx_position]))
        pairs = np.stack([np.arange(len(ues)), np.zeros(len(ues), dtype=int)], axis=1)
        power = self.model.predict(pairs, self.p.tx_power_dbm)
        noise = self.rng.normal(0.0, self.p.noise_db, len(ues))
        profiles = (self.model.power_delay_profiles(pairs, 1.0 / self.p.bandwidth_hz) if self.p.profiles
                    else [None] * len(ues))
        for ue, pw, n, prof in zip(ues, power, noise, profiles, strict=True):
            if not np.isfinite(pw):
                continue  # no path: below any receiver's sensitivity, nothing reported
            q = positions[ue]
            sample = {
                "time_s": t, "rx_x": float(q[0]), "rx_y": float(q[1]), "rx_z": float(q[2]),
                "tx_x": float(self.p.tx_position[0]), "tx_y": float(self.p.tx_position[1]),
                "tx_z": float(self.p.tx_position[2]), "power_dbm": round(float(pw + n), 4),
                "tx_power_dbm": self.p.tx_power_dbm, "frequency_hz": self.p.frequency_hz,
                "bandwidth_hz": self.p.bandwidth_hz}
            if prof is not None:
                taps = (self.p.tx_power_dbm + 10.0 * np.log10(prof[1])
                        + self.rng.normal(0.0, self.p.noise_db, len(prof[1])))
                sample.update(pdp_delay_s=[float(v) for v in prof[0]], pdp_power_dbm=[round(float(v), 4) for v in taps])
            yield f"{TOPIC}.{ue}", sample

    def state(self):
        return {"rng": self.rng.bit_generator.state}

    def restore(self, state):
        self.rng.bit_generator.state = state["rng"]
