"""Learning a scene's radio materials from measurements by gradient descent through Sionna RT
(differentiable ray tracing; the method of Hoydis et al., "Learning radio environments by
differentiable ray tracing", 2024).

:func:`fit_materials` takes a scene (loaded at the measurements' carrier), measurements
(:class:`~caviar_plugins.twin.measurements.Measurements`) and :class:`FitSettings`, and:

1. keeps a held-out share of the samples out of the fit (``holdout``, drawn with ``seed``);
2. asks which properties the fit samples can identify: the sensitivity of the predicted dBm to
   each property (a central difference in its log), and the Cramér–Rao bound of each one's
   log given ``noise_db`` of measurement noise. A property whose bound is wider than
   ``max_log_std`` (0.2: about ±20 %), alone or because another one explains the same data,
   is not learned and is reported as not identifiable;
3. searches each identifiable property coarsely over its physical range
   (:data:`SEARCH_RANGE`, ``search_points`` values, ``search_sweeps`` rounds, the others held):
   a wall's reflection oscillates with its permittivity (the two faces of a slab of
   ``thickness`` interfere), so the error has several minima and a descent from a wrong guess
   stops in the nearest one;
4. descends (Adam) on the mean squared error in dB of the fit samples with respect to the
   identifiable properties' logs (ε_r − 1, σ and the logit of S: each stays in its physical
   range), with Dr.Jit's gradient through Sionna's field computation, until the error stops
   falling by ``plateau`` over ``patience`` iterations or ``iterations`` are done;
5. reports the RMSE in dB before and after on the fit and the held-out samples (the honest
   figure), and the learned values beside the starting ones.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from caviar_plugins.rt.materials import PROPERTIES, scene_materials, split_material, used_materials
from caviar_plugins.rt.received_power import ReceivedPower, Unknown
from caviar_plugins.rt.settings import TraceSettings
from caviar_plugins.twin.measurements import Measurements

FIT_RAYS = TraceSettings(samples_per_src=200_000, max_depth=3, diffuse_reflection=False, refraction=False,
                         diffraction=False, shoot_cache=False)
"""How a fit traces by default: 2e5 rays to depth 3, line of sight and specular reflections
(what received power at street level is made of; add diffraction or diffuse reflection with
``raytracing``: diffuse reflection is what makes a scattering coefficient identifiable)."""
LOWER = {"relative_permittivity": 1.0 + 1e-3, "conductivity": 1e-6, "scattering_coefficient": 1e-4}
SEARCH_RANGE = {"relative_permittivity": (1.5, 80.0), "conductivity": (1e-3, 10.0),
                "scattering_coefficient": (0.01, 0.9)}
"""Where the coarse search looks for each property (the span of ITU-R P.2040's materials)."""


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """What a material fit learns and how (``caviar-core fit-scene``, the ``scene-fitter``
    module)."""

    learn: tuple[str, ...] = ("relative_permittivity", "conductivity")
    """The properties learned per material (of ``relative_permittivity``, ``conductivity``,
    ``scattering_coefficient``)."""
    materials: tuple[str, ...] = ()
    """The materials learned (empty: every material an object of the scene uses)."""
    groups: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    """Object groups with a material of their own: ``{group: (object name globs…)}`` (e.g.
    the buildings of one block); each is learned as a material of that name."""
    holdout: float = 0.2
    """The share of samples never used for fitting, on which the fit is judged."""
    iterations: int = 100
    """Gradient steps at most."""
    learning_rate: float = 0.02
    """Adam's step, in the logs of the properties (0.02: about 2 % per step at first; a
    slab's oscillation leaves basins about ±5 % wide in ε_r, which larger steps jump)."""
    plateau: float = 1e-3
    """Stop when the fit error fell by less than this share over ``patience`` steps."""
    patience: int = 5
    noise_db: float = 1.0
    """The measurements' noise (dB, one standard deviation): it sets the identifiability
    bound."""
    max_log_std: float = 0.2
    """A property is learned only if the Cramér–Rao bound of its log is within this."""
    seed: int = 0
    """Draws the held-out samples."""
    search_points: int = 40
    """Values per property in the coarse search (:func:`search_grid`). The permittivity's
    grid must be finer than the slab's oscillation: a step in √ε_r of at most about
    λ/(4·thickness) (40 points over 1.5–80: 0.2, enough for 10 cm walls at 3.5 GHz)."""
    search_sweeps: int = 2
    """Rounds of the coarse search over all properties (0: none, descend from the start)."""

    def __post_init__(self):
        for p in self.learn:
            if p not in PROPERTIES:
                raise ValueError(f"learn: '{p}' is not a material property (expected {', '.join(PROPERTIES)})")
        if not self.learn:
            raise ValueError("learn: expected at least one property")
        if not 0.0 <= self.holdout < 1.0:
            raise ValueError(f"holdout: expected a share in [0, 1), got {self.holdout!r}")
        if isinstance(self.search_sweeps, bool) or not isinstance(self.search_sweeps, int) or self.search_sweeps < 0:
            raise ValueError(f"search_sweeps: expected a whole number >= 0, got {self.search_sweeps!r}")
        for key in ("iterations", "patience", "search_points"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{key}: expected a whole number >= 1, got {v!r}")
        for key in ("learning_rate", "noise_db", "max_log_std", "plateau"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key}: expected a number > 0, got {v!r}")


def to_log(prop: str, v: float) -> float:
    """The unconstrained coordinate a fit moves ``prop`` in."""
    v = max(v, LOWER[prop])
    if prop == "relative_permittivity":
        return math.log(v - 1.0)
    if prop == "scattering_coefficient":
        v = min(v, 1 - 1e-4)
        return math.log(v / (1 - v))
    return math.log(v)


def from_log(prop: str, x: float) -> float:
    if prop == "relative_permittivity":
        return 1.0 + math.exp(x)
    if prop == "scattering_coefficient":
        return 1.0 / (1.0 + math.exp(-x))
    return math.exp(x)


def dvalue_dlog(prop: str, v: float) -> float:
    if prop == "relative_permittivity":
        return v - 1.0
    if prop == "scattering_coefficient":
        return v * (1.0 - v)
    return v


@dataclasses.dataclass
class Identifiability:
    """What the fit samples can tell about each unknown."""

    sensitivity_db: dict[Unknown, float]
    """RMS over the fit samples of the change in predicted dBm per unit change of the
    property's log (about per 100 %)."""
    log_std: dict[Unknown, float]
    """The Cramér–Rao bound of each unknown's log (inf: not determined)."""
    identifiable: list[Unknown]
    ambiguous: dict[Unknown, list[float]] = dataclasses.field(default_factory=dict)
    """Unknowns that other, separate values fit as well as the learned one (within the noise:
    a likelihood-ratio test at 95 %, Δ(Σ err²) ≤ 3.84·noise_db²), with those values: the
    coarse search saw them, and the data cannot choose."""

    def as_json(self) -> dict[str, Any]:
        return {f"{m}.{p}": {"sensitivity_db": round(self.sensitivity_db[(m, p)], 4),
                             "log_std": (round(self.log_std[(m, p)], 4) if math.isfinite(self.log_std[(m, p)])
                                         else None),
                             "identifiable": (m, p) in self.identifiable and (m, p) not in self.ambiguous,
                             **({"ambiguous_with": [round(v, 4) for v in self.ambiguous[(m, p)]]}
                                if (m, p) in self.ambiguous else {})}
                for (m, p) in self.sensitivity_db}


@dataclasses.dataclass
class FitResult:
    start: dict[Unknown, float]
    learned: dict[Unknown, float]
    identifiability: Identifiability
    rmse_db: dict[str, dict[str, float]]
    """``{"fit"|"held_out": {"before": dB, "after": dB}}``."""
    history: list[dict[str, Any]]
    samples: dict[str, int]
    stopped: str
    materials: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Every material's values after the fit (:class:`~caviar_plugins.rt.materials.MaterialValues`)."""
    groups: dict[str, list[str]] = dataclasses.field(default_factory=dict)
    predicted_dbm: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """``{"before"|"after": dBm per sample}``."""
    holdout_mask: np.ndarray | None = None

    def as_json(self) -> dict[str, Any]:
        return {"learned": {f"{m}.{p}": {"start": self.start[(m, p)], "learned": self.learned[(m, p)]}
                            for (m, p) in self.start},
                "identifiability": self.identifiability.as_json(),
                "rmse_db": self.rmse_db, "samples": self.samples, "stopped": self.stopped,
                "iterations": sum(r["phase"] == "descent" for r in self.history) - 1,
                "search_evaluations": sum(r["phase"] == "search" for r in self.history), "groups": self.groups,
                "materials": {k: v.as_dict() for k, v in self.materials.items()},
                "history": self.history}


def rmse(pred: np.ndarray, measured: np.ndarray, mask: np.ndarray) -> float:
    m = mask & np.isfinite(pred)
    return float(np.sqrt(np.mean((pred[m] - measured[m]) ** 2))) if m.any() else float("nan")


class _Problem:
    """The measurements placed in the scene, and predictions at given unknowns' logs."""

    def __init__(self, model: ReceivedPower, data: Measurements, unknowns: list[Unknown]):
        self.model, self.data, self.unknowns = model, data, unknowns
        self.frozen: dict[Unknown, float] = {}
        """Unknowns held at their starting value (not identifiable), whatever ``x`` says."""
        sites, tx_index = data.transmitters()
        model.place(data.rx, sites)
        self.pairs = np.stack([np.arange(len(data)), tx_index], axis=1)

    def values(self, x: np.ndarray) -> dict[Unknown, float]:
        return {u: self.frozen[u] if u in self.frozen else from_log(u[1], float(xi))
                for u, xi in zip(self.unknowns, x, strict=True)}

    def predict(self, x: np.ndarray) -> np.ndarray:
        return self.model.predict(self.pairs, self.data.tx_power_dbm, self.values(x))

    def jacobian(self, x: np.ndarray, step: float = 0.05) -> np.ndarray:
        """d(predicted dBm)/d(log) per sample and unknown, by central differences."""
        cols = []
        for k in range(len(x)):
            up, down = x.copy(), x.copy()
            up[k] += step
            down[k] -= step
            with np.errstate(invalid="ignore"):  # a pair without a path is -inf both ways: nan, left out
                cols.append((self.predict(up) - self.predict(down)) / (2 * step))
        self.predict(x)
        return np.stack(cols, axis=1) if cols else np.zeros((len(self.data), 0))


def identifiability(J: np.ndarray, mask: np.ndarray, unknowns: list[Unknown], settings: FitSettings) -> Identifiability:
    """Which unknowns the rows ``mask`` of ``J`` determine (see the module's step 2): drops
    the worst-bounded unknown until every one left is within ``max_log_std``."""
    rows = mask & np.all(np.isfinite(J), axis=1)
    Jf = J[rows]
    sens = {u: float(np.sqrt(np.mean(Jf[:, k] ** 2))) if len(Jf) else 0.0 for k, u in enumerate(unknowns)}
    keep = list(range(len(unknowns)))
    std: dict[Unknown, float] = {u: math.inf for u in unknowns}
    while keep:
        F = Jf[:, keep].T @ Jf[:, keep] / settings.noise_db**2
        if np.linalg.cond(F) > 1e12:  # some combination is not seen at all: drop the least seen
            weakest = min(range(len(keep)), key=lambda i: sens[unknowns[keep[i]]])
            keep.pop(weakest)
            continue
        stds = np.sqrt(np.maximum(np.diag(np.linalg.inv(F)), 0))
        for k, s in zip(keep, stds, strict=True):
            std[unknowns[k]] = float(s)
        worst = int(np.argmax(stds))
        if stds[worst] <= settings.max_log_std:
            break
        keep.pop(worst)
    return Identifiability(sens, std, [unknowns[k] for k in keep])


def search_grid(prop: str, n: int) -> np.ndarray:
    """``n`` values of ``prop`` over :data:`SEARCH_RANGE`: evenly spaced in √ε_r for the
    permittivity (a slab's reflection oscillates with its electrical thickness, ∝ √ε_r),
    in log σ for the conductivity, linearly for the scattering coefficient."""
    lo, hi = SEARCH_RANGE[prop]
    if prop == "relative_permittivity":
        return np.linspace(np.sqrt(lo), np.sqrt(hi), n) ** 2
    if prop == "conductivity":
        return np.geomspace(lo, hi, n)
    return np.linspace(lo, hi, n)


def rival_minima(values: np.ndarray, sse: np.ndarray, threshold: float) -> list[float]:
    """The values at local minima of a profile ``sse`` (over ``values``) other than the best's
    own basin whose Σ err² is within ``threshold`` of the best."""
    best = int(np.argmin(sse))
    # the best's basin: from its minimum out to the maxima on either side
    lo = best
    while lo > 0 and sse[lo - 1] >= sse[lo]:
        lo -= 1
    hi = best
    while hi < len(sse) - 1 and sse[hi + 1] >= sse[hi]:
        hi += 1
    out = []
    for i in range(len(sse)):
        if lo <= i <= hi:
            continue
        left = i == 0 or sse[i] <= sse[i - 1]
        right = i == len(sse) - 1 or sse[i] <= sse[i + 1]
        if left and right and sse[i] - sse[best] <= threshold:
            out.append(float(values[i]))
    return out


def coarse_search(problem: _Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                  settings: FitSettings, history: list[dict[str, Any]],
                  progress: Callable[[dict[str, Any]], None] | None) -> tuple[np.ndarray, dict[Unknown, list[float]]]:
    """Step 3 of the module: per free unknown in turn, the best of ``search_points`` values
    over its range; ``search_sweeps`` rounds. Returns the best logs, and per unknown the
    other values that its last profile says fit as well (:func:`rival_minima`)."""
    x = x.copy()
    measured = problem.data.power_dbm
    best = rmse(problem.predict(x), measured, fit_mask)
    rivals: dict[Unknown, list[float]] = {}
    n_fit = int(fit_mask.sum())
    for sweep in range(settings.search_sweeps):
        for k in np.flatnonzero(free):
            prop = problem.unknowns[k][1]
            grid = search_grid(prop, settings.search_points)
            profile = []
            for v in grid:
                trial = x.copy()
                trial[k] = to_log(prop, float(v))
                pred = problem.predict(trial)
                err = rmse(pred, measured, fit_mask)
                row = {"phase": "search", "sweep": sweep, "fit_rmse_db": err,
                       "held_out_rmse_db": rmse(pred, measured, held),
                       **{f"{m}.{p}": val for (m, p), val in problem.values(trial).items()}}
                history.append(row)
                if progress is not None:
                    progress(row)
                profile.append(n_fit * err**2 if np.isfinite(err) else np.inf)
                if err < best:
                    best, x = err, trial
            found = rival_minima(grid, np.array(profile), 3.84 * settings.noise_db**2)
            rivals.pop(problem.unknowns[k], None)
            if found:
                rivals[problem.unknowns[k]] = found
    return x, rivals


def fit_materials(scene: Any, data: Measurements, settings: FitSettings = FitSettings(),
                  raytracing: TraceSettings = FIT_RAYS, *, run_seed: int = 0,
                  progress: Callable[[dict[str, Any]], None] | None = None) -> FitResult:
    """Learns ``scene``'s materials from ``data`` (the module's steps 1–4); the scene is left
    with the learned values."""
    scene.frequency = data.frequency_hz
    groups = {g: split_material(scene, g, patterns) for g, patterns in settings.groups.items()}
    materials = list(settings.materials) or used_materials(scene)
    model = ReceivedPower(scene, raytracing, seed=run_seed)
    start_values = scene_materials(scene)
    unknowns = [(m, p) for m in materials for p in settings.learn]
    for m, _ in unknowns:
        if m not in start_values:
            raise ValueError(f"materials: '{m}' is not a material an object of the scene uses "
                             f"({', '.join(sorted(start_values))})")
    problem = _Problem(model, data, unknowns)
    n = len(data)
    held = np.zeros(n, dtype=bool)
    n_held = int(round(settings.holdout * n))
    held[np.random.default_rng(settings.seed).permutation(n)[:n_held]] = True
    fit_mask = ~held
    start = {u: getattr(start_values[u[0]], u[1]) for u in unknowns}
    x0 = np.array([to_log(u[1], start[u]) for u in unknowns])
    measured = data.power_dbm
    before = problem.predict(x0)
    ident = identifiability(problem.jacobian(x0), fit_mask, unknowns, settings)
    free = np.array([u in ident.identifiable for u in unknowns])
    problem.frozen = {u: start[u] for u, f in zip(unknowns, free, strict=True) if not f}
    history: list[dict[str, Any]] = []
    x, ident.ambiguous = coarse_search(problem, x0, free, fit_mask, held, settings, history, progress)
    m1, m2 = np.zeros_like(x0), np.zeros_like(x0)
    best = (math.inf, x.copy())
    stopped = f"{settings.iterations} iterations"
    for it in range(settings.iterations + 1):
        values = problem.values(x)
        pred, loss, grads = model.loss_and_gradient(problem.pairs, data.tx_power_dbm, measured,
                                                    fit_mask.astype(float), values)
        row = {"phase": "descent", "iteration": it, "fit_rmse_db": rmse(pred, measured, fit_mask),
               "held_out_rmse_db": rmse(pred, measured, held),
               **{f"{m}.{p}": values[(m, p)] for (m, p) in unknowns}}
        history.append(row)
        if progress is not None:
            progress(row)
        if loss < best[0]:
            best = (loss, x.copy())
        if not free.any():
            stopped = "nothing identifiable to learn"
            break
        if it >= settings.patience:
            old = history[-1 - settings.patience]["fit_rmse_db"] ** 2
            if old - loss < settings.plateau * old:
                stopped = f"plateau after {it} iterations"
                break
        if it == settings.iterations:
            break
        g = np.array([grads[u] * dvalue_dlog(u[1], values[u]) for u in unknowns]) * free
        m1 = 0.9 * m1 + 0.1 * g
        m2 = 0.999 * m2 + 0.001 * g**2
        step = settings.learning_rate * (m1 / (1 - 0.9 ** (it + 1))) / (np.sqrt(m2 / (1 - 0.999 ** (it + 1))) + 1e-12)
        x = x - np.where(free, step, 0.0)
    x_best = best[1]
    after = problem.predict(x_best)
    learned = problem.values(x_best)
    return FitResult(
        start=start, learned=learned, identifiability=ident,
        rmse_db={"fit": {"before": rmse(before, measured, fit_mask), "after": rmse(after, measured, fit_mask)},
                 "held_out": {"before": rmse(before, measured, held), "after": rmse(after, measured, held)}},
        history=history,
        samples={"total": n, "fit": int(fit_mask.sum()), "held_out": int(held.sum()),
                 "without_path": int((~np.isfinite(after)).sum())},
        stopped=stopped, materials=scene_materials(scene), groups=groups,
        predicted_dbm={"before": before, "after": after}, holdout_mask=held)
