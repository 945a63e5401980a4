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
JACOBIAN_STEP = 0.01
"""The central difference's step in a property's log for the Levenberg–Marquardt Jacobian."""
MAX_LOG_STEP = 0.3
"""A Levenberg–Marquardt step moves no log by more than this (about ±35 %)."""
METHODS = ("lm", "adam")
CONFOUNDED = 0.9
"""Two unknowns whose sensitivities over the fit samples align this closely (|cosine|) are
confounded: the data see their combination."""


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
    method: str = "lm"
    """How the fit descends after the search: ``"lm"`` (Levenberg–Marquardt on the residuals,
    the Jacobian by central differences) or ``"adam"`` (Adam on the gradient of the squared
    error by automatic differentiation through Sionna RT)."""
    learning_rate: float = 0.02
    """With ``method = "adam"``: Adam's step, in the logs of the properties (0.02: about 2 % per step at first; a
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
    search_points: int = 160
    """Values per property in the coarse search (:func:`search_grid`). The permittivity's
    grid must resolve the slab's oscillation, whose period in √ε_r is λ/(2·thickness) (0.43
    for 10 cm walls at 3.5 GHz) and whose minima are a fraction of it wide: 160 points over
    1.5–80 step 0.05 in √ε_r, an eighth of that period. (With 40, a step of half a period,
    the grid's best was an aliased basin: two walls' permittivities 18 % and 43 % off on
    the street canyon of the tests.)"""
    search_sweeps: int = 3
    """Rounds of a coarse search over all properties and a descent from its best (0: no
    search, descend from the start); the rounds stop early when one finds nothing better.
    A second round catches two properties that trade off (a wall's permittivity that the
    first sweep set to make up for another's wrong start)."""
    restarts: int = 8
    """Then this many more rounds from random values of every learned property (drawn over
    :data:`SEARCH_RANGE` with ``seed``), each a search sweep and a descent: two properties
    that trade off (a high permittivity on one wall making up for a low one on another) hold
    a coordinate search in a wrong pair of basins, which a start elsewhere leaves. The best
    round wins; another round's minimum that fits as well within the noise (the likelihood
    bound of :class:`Identifiability`) makes the values it differs in ambiguous."""

    def __post_init__(self):
        for p in self.learn:
            if p not in PROPERTIES:
                raise ValueError(f"learn: '{p}' is not a material property (expected {', '.join(PROPERTIES)})")
        if not self.learn:
            raise ValueError("learn: expected at least one property")
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 <= self.holdout < 1.0:
            raise ValueError(f"holdout: expected a share in [0, 1), got {self.holdout!r}")
        if isinstance(self.search_sweeps, bool) or not isinstance(self.search_sweeps, int) or self.search_sweeps < 0:
            raise ValueError(f"search_sweeps: expected a whole number >= 0, got {self.search_sweeps!r}")
        if isinstance(self.restarts, bool) or not isinstance(self.restarts, int) or self.restarts < 0:
            raise ValueError(f"restarts: expected a whole number >= 0, got {self.restarts!r}")
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
    learned: list[Unknown] = dataclasses.field(default_factory=list)
    """The unknowns the fit moved: those within the bound, and those a likelihood-ratio test
    found the data see although their bound is wide (:func:`likelihood_ratio_inclusion`)."""
    confounded: dict[Unknown, list[Unknown]] = dataclasses.field(default_factory=dict)
    """Learned unknowns whose effect on the data is nearly that of an unknown left at its
    start value (:data:`CONFOUNDED`): what they learn makes up for that one too, so they are
    not reported as identified (the prediction still gains)."""
    ambiguous: dict[Unknown, list[float]] = dataclasses.field(default_factory=dict)
    """Unknowns that other, separate values fit as well as the learned one (within the noise:
    a likelihood-ratio test at 95 %, Δ(Σ err²) ≤ 3.84·noise_db²), with those values: the
    coarse search saw them, and the data cannot choose."""

    def identified(self, u: Unknown) -> bool:
        """Learned, and neither confounded with a fixed unknown nor ambiguous."""
        return u in self.identifiable and u not in self.confounded and u not in self.ambiguous

    def as_json(self) -> dict[str, Any]:
        return {f"{m}.{p}": {"sensitivity_db": round(self.sensitivity_db[(m, p)], 4),
                             "log_std": (round(self.log_std[(m, p)], 4) if math.isfinite(self.log_std[(m, p)])
                                         else None),
                             "learned": (m, p) in self.learned, "identifiable": self.identified((m, p)),
                             **({"confounded_with": [f"{a}.{b}" for a, b in self.confounded[(m, p)]]}
                                if (m, p) in self.confounded else {}),
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
    cost: dict[str, int] = dataclasses.field(default_factory=dict)
    """``{"traces": whole traces, "field_evaluations": fields computed on traced paths}``."""

    def as_json(self) -> dict[str, Any]:
        return {"learned": {f"{m}.{p}": {"start": self.start[(m, p)], "learned": self.learned[(m, p)]}
                            for (m, p) in self.start},
                "identifiability": self.identifiability.as_json(),
                "rmse_db": self.rmse_db, "samples": self.samples, "stopped": self.stopped,
                "iterations": sum(r["phase"] == "descent" for r in self.history) - 1,
                "search_evaluations": sum(r["phase"] == "search" for r in self.history), "groups": self.groups,
                "materials": {k: v.as_dict() for k, v in self.materials.items()}, "cost": self.cost,
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
    confounded: dict[Unknown, list[Unknown]] = {}
    for k in sorted(set(range(len(unknowns))) - set(keep)):
        # a property left out although the data see it alone: the kept ones it trades off
        # with absorb its error (a ground's permittivity and conductivity both set its
        # reflection loss), so their learned values hold only for its fixed value
        seen_alone = sens[unknowns[k]] > 0 and settings.noise_db / (
            math.sqrt(len(Jf)) * sens[unknowns[k]]) <= settings.max_log_std
        if not seen_alone or not keep:
            continue
        cols = [*keep, k]
        F = Jf[:, cols].T @ Jf[:, cols]
        scale = np.sqrt(np.maximum(np.diag(F), 1e-300))
        corr = F / np.outer(scale, scale)  # the sensitivities' alignment: 1 = the same effect
        for i, kept in enumerate(keep):
            if abs(corr[i, -1]) >= CONFOUNDED:
                confounded.setdefault(unknowns[kept], []).append(unknowns[k])
    return Identifiability(sens, std, [unknowns[k] for k in keep], confounded=confounded)


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


def _record(problem: _Problem, x: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
            history: list[dict[str, Any]], progress: Callable[[dict[str, Any]], None] | None,
            pred: np.ndarray | None = None, **label: Any) -> float:
    """Appends a history row for ``x`` (predicting it unless ``pred`` is given); returns
    the fit RMSE (dB)."""
    if pred is None:
        pred = problem.predict(x)
    measured = problem.data.power_dbm
    err = rmse(pred, measured, fit_mask)
    row = {**label, "fit_rmse_db": err, "held_out_rmse_db": rmse(pred, measured, held),
           **{f"{m}.{p}": val for (m, p), val in problem.values(x).items()}}
    history.append(row)
    if progress is not None:
        progress(row)
    return err


def coarse_search(problem: _Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                  settings: FitSettings, history: list[dict[str, Any]],
                  progress: Callable[[dict[str, Any]], None] | None,
                  sweep: int = 0, restart: int | None = None) -> tuple[np.ndarray, dict[Unknown, list[float]]]:
    """Step 3 of the module, one sweep: per free unknown in turn, the best of
    ``search_points`` values over its range, the others held. Returns the best logs, and per
    unknown the other values that its profile says fit as well (:func:`rival_minima`)."""
    x = x.copy()
    best = rmse(problem.predict(x), problem.data.power_dbm, fit_mask)
    rivals: dict[Unknown, list[float]] = {}
    n_fit = int(fit_mask.sum())
    for k in np.flatnonzero(free):
        prop = problem.unknowns[k][1]
        grid = search_grid(prop, settings.search_points)
        profile = []
        for v in grid:
            trial = x.copy()
            trial[k] = to_log(prop, float(v))
            label: dict[str, Any] = {"sweep": sweep} if restart is None else {"restart": restart}
            err = _record(problem, trial, fit_mask, held, history, progress, None, phase="search", **label)
            profile.append(n_fit * err**2 if np.isfinite(err) else np.inf)
            if err < best:
                best, x = err, trial
        found = rival_minima(grid, np.array(profile), 3.84 * settings.noise_db**2)
        if found:
            rivals[problem.unknowns[k]] = found
    return x, rivals


def _iteration(history: list[dict[str, Any]]) -> int:
    return sum(r["phase"] == "descent" for r in history)


def _plateaued(history: list[dict[str, Any]], settings: FitSettings, since: int) -> bool:
    errs = [r["fit_rmse_db"] ** 2 for r in history[since:] if r["phase"] == "descent"]
    return len(errs) > settings.patience and errs[-1 - settings.patience] - errs[-1] < settings.plateau * errs[
        -1 - settings.patience]


def levenberg_marquardt(problem: _Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray,
                        held: np.ndarray, settings: FitSettings, history: list[dict[str, Any]],
                        progress: Callable[[dict[str, Any]], None] | None) -> tuple[np.ndarray, str]:
    """Step 4 of the module (``method = "lm"``): Levenberg–Marquardt on the fit samples'
    residuals in dB, in the free unknowns' logs, with the Jacobian by central differences of
    :data:`JACOBIAN_STEP` (1 %: well inside a slab's ±5 % basins). A step is taken only if
    it lowers the fit RMSE; the damping grows until one does, and the descent stops when none
    does, on a plateau or after ``iterations``. Unlike a fixed-step descent it moves
    correlated properties together (two walls' permittivities that trade off), in few
    iterations."""
    idx = np.flatnonzero(free)
    measured = problem.data.power_dbm
    since = len(history)
    pred = problem.predict(x)
    err = _record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
                  iteration=_iteration(history))
    damping = 1e-3
    for _ in range(settings.iterations):
        if _plateaued(history, settings, since):
            return x, f"plateau after {_iteration(history) - 1} iterations"
        J = problem.jacobian(x, step=JACOBIAN_STEP)[:, idx]
        rows = fit_mask & np.isfinite(pred) & np.all(np.isfinite(J), axis=1)
        if not rows.any():
            return x, "no fitted sample has a path"
        r, Jr = pred[rows] - measured[rows], J[rows]
        A, g = Jr.T @ Jr, Jr.T @ r
        for _try in range(12):
            delta = -np.linalg.solve(A + damping * (np.diag(np.diag(A)) + 1e-9 * np.eye(len(idx))), g)
            delta *= min(1.0, MAX_LOG_STEP / max(float(np.max(np.abs(delta))), 1e-12))
            trial = x.copy()
            trial[idx] += delta
            trial_pred = problem.predict(trial)
            trial_err = rmse(trial_pred, measured, fit_mask)
            if np.isfinite(trial_err) and trial_err < err:
                x, pred, err = trial, trial_pred, trial_err
                damping = max(damping / 3.0, 1e-9)
                break
            damping *= 4.0
        else:
            problem.predict(x)
            return x, f"converged after {_iteration(history) - 1} iterations (no step lowers the error)"
        _record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
                iteration=_iteration(history))
    return x, f"{settings.iterations} iterations"


def adam(problem: _Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
         settings: FitSettings, history: list[dict[str, Any]],
         progress: Callable[[dict[str, Any]], None] | None) -> tuple[np.ndarray, str]:
    """Step 4 of the module (``method = "adam"``): Adam on the mean squared error in dB with
    the gradient by Dr.Jit's automatic differentiation through Sionna's field computation,
    ``learning_rate`` in the logs; returns the best point it visited."""
    model, data, unknowns = problem.model, problem.data, problem.unknowns
    measured = data.power_dbm
    m1, m2 = np.zeros_like(x), np.zeros_like(x)
    best = (math.inf, x.copy())
    since = len(history)
    for it in range(settings.iterations + 1):
        values = problem.values(x)
        pred, loss, grads = model.loss_and_gradient(problem.pairs, data.tx_power_dbm, measured,
                                                    fit_mask.astype(float), values)
        _record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
                iteration=_iteration(history))
        if loss < best[0]:
            best = (loss, x.copy())
        if _plateaued(history, settings, since):
            return best[1], f"plateau after {it} iterations"
        if it == settings.iterations:
            break
        g = np.array([grads[u] * dvalue_dlog(u[1], values[u]) for u in unknowns]) * free
        m1 = 0.9 * m1 + 0.1 * g
        m2 = 0.999 * m2 + 0.001 * g**2
        step = settings.learning_rate * (m1 / (1 - 0.9 ** (it + 1))) / (np.sqrt(m2 / (1 - 0.999 ** (it + 1))) + 1e-12)
        x = x - np.where(free, step, 0.0)
    return best[1], f"{settings.iterations} iterations"


def restart_rounds(problem: _Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                   settings: FitSettings, history: list[dict[str, Any]],
                   progress: Callable[[dict[str, Any]], None] | None, ident: Identifiability) -> np.ndarray:
    """``settings.restarts`` rounds from random values (see :attr:`FitSettings.restarts`):
    returns the best logs, and adds to ``ident.ambiguous`` the values of every other round's
    minimum that fits within the likelihood bound and lies outside the best's bound."""
    measured = problem.data.power_dbm
    rng = np.random.default_rng(settings.seed + 1)
    descend = levenberg_marquardt if settings.method == "lm" else adam
    minima = [(rmse(problem.predict(x), measured, fit_mask), x)]
    for r in range(settings.restarts):
        trial = x.copy()
        for k in np.flatnonzero(free):
            prop = problem.unknowns[k][1]
            grid = search_grid(prop, settings.search_points)
            if prop == "relative_permittivity":
                v = rng.uniform(np.sqrt(grid[0]), np.sqrt(grid[-1])) ** 2
            elif prop == "conductivity":
                v = math.exp(rng.uniform(math.log(grid[0]), math.log(grid[-1])))
            else:
                v = rng.uniform(grid[0], grid[-1])
            trial[k] = to_log(prop, float(v))
        if settings.search_sweeps:
            trial, _ = coarse_search(problem, trial, free, fit_mask, held, settings, history, progress, restart=r)
        trial, _ = descend(problem, trial, free, fit_mask, held, settings, history, progress)
        minima.append((rmse(problem.predict(trial), measured, fit_mask), trial))
    err, best = min(minima, key=lambda m: m[0] if np.isfinite(m[0]) else np.inf)
    n_fit = int(fit_mask.sum())
    for e, other in minima:
        if not np.isfinite(e) or n_fit * (e**2 - err**2) > 3.84 * settings.noise_db**2:
            continue
        for k in np.flatnonzero(free):
            if abs(other[k] - best[k]) > settings.max_log_std:
                u = problem.unknowns[k]
                value = from_log(u[1], float(other[k]))
                rivals = ident.ambiguous.setdefault(u, [])
                if all(abs(to_log(u[1], v) - other[k]) > settings.max_log_std for v in rivals):
                    rivals.append(value)
    problem.predict(best)
    return best


def likelihood_ratio_inclusion(problem: _Problem, x: np.ndarray, free: np.ndarray, start: dict[Unknown, float],
                               fit_mask: np.ndarray, held: np.ndarray, settings: FitSettings,
                               history: list[dict[str, Any]], progress: Callable[[dict[str, Any]], None] | None
                               ) -> tuple[np.ndarray, list[Unknown]]:
    """The global check the local bound cannot make: for each property left at its start, a
    search over it and a descent of it with the learned ones; if that lowers the fit samples'
    Σ err² by more than a likelihood-ratio test at 95 % allows (3.84·noise_db²), the data do
    see it (a ground's conductivity, whose effect its permittivity mimics near the start but
    not over the whole flight): it is learned from then on (``free`` is updated). Returns the
    logs and the properties so learned."""
    measured = problem.data.power_dbm
    n_fit = int(fit_mask.sum())
    descend = levenberg_marquardt if settings.method == "lm" else adam
    err = rmse(problem.predict(x), measured, fit_mask)
    seen: list[Unknown] = []
    for k in [int(k) for k in np.flatnonzero(~free)]:
        u = problem.unknowns[k]
        trial_free = free.copy()
        trial_free[k] = True
        problem.frozen = {v: start[v] for v, f in zip(problem.unknowns, trial_free, strict=True) if not f}
        only = np.zeros_like(free)
        only[k] = True
        trial, _ = coarse_search(problem, x, only, fit_mask, held, settings, history, progress, sweep=-1)
        trial, _ = descend(problem, trial, trial_free, fit_mask, held, settings, history, progress)
        trial_err = rmse(problem.predict(trial), measured, fit_mask)
        if np.isfinite(trial_err) and n_fit * (err**2 - trial_err**2) > 3.84 * settings.noise_db**2:
            x, err, free[k] = trial, trial_err, True
            seen.append(u)
    problem.frozen = {v: start[v] for v, f in zip(problem.unknowns, free, strict=True) if not f}
    problem.predict(x)
    return x, seen


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
    x, stopped = x0.copy(), "nothing identifiable to learn"
    last = math.inf
    for sweep in range(max(settings.search_sweeps, 1)):
        if settings.search_sweeps:
            x, rivals = coarse_search(problem, x, free, fit_mask, held, settings, history, progress, sweep=sweep)
            ident.ambiguous = rivals
        if not free.any():
            break
        descend = levenberg_marquardt if settings.method == "lm" else adam
        x, stopped = descend(problem, x, free, fit_mask, held, settings, history, progress)
        err = rmse(problem.predict(x), measured, fit_mask)
        if math.isfinite(last) and last - err <= settings.plateau * last:  # this round found nothing better
            break
        last = err
    if not free.any():
        _record(problem, x, fit_mask, held, history, progress, phase="descent", iteration=0)
    else:
        x = restart_rounds(problem, x, free, fit_mask, held, settings, history, progress, ident)
        # the bound at the estimate, where it belongs: a property that the start hid (a
        # ground's conductivity barely matters at a low permittivity) may show at the solution
        frozen, problem.frozen = problem.frozen, {}  # every unknown's column, the held ones' too
        at_solution = identifiability(problem.jacobian(x), fit_mask, unknowns, settings)
        problem.frozen = frozen
        more = np.array([u in at_solution.identifiable for u in unknowns]) & ~free
        if more.any():
            free |= more
            problem.frozen = {u: start[u] for u, f in zip(unknowns, free, strict=True) if not f}
            descend = levenberg_marquardt if settings.method == "lm" else adam
            x, stopped = descend(problem, x, free, fit_mask, held, settings, history, progress)
        x, seen = likelihood_ratio_inclusion(problem, x, free, start, fit_mask, held, settings, history, progress)
        if seen:
            stopped = f"{stopped}; then learned {', '.join(f'{m}.{p}' for m, p in seen)} (likelihood-ratio test)"
        if seen or more.any():  # the bound where the fit ended
            frozen, problem.frozen = problem.frozen, {}
            at_solution = identifiability(problem.jacobian(x), fit_mask, unknowns, settings)
            problem.frozen = frozen
        at_solution.learned = [u for u, f in zip(unknowns, free, strict=True) if f]
        at_solution.confounded = {u: fixed for u, fixed in
                                  ((u, [v for v in vs if v not in at_solution.learned])
                                   for u, vs in at_solution.confounded.items()) if fixed}
        at_solution.ambiguous = ident.ambiguous
        ident = at_solution
    best = min((r for r in history), key=lambda r: r["fit_rmse_db"] if np.isfinite(r["fit_rmse_db"]) else np.inf,
               default=None)
    x_best = x if best is None else np.array([to_log(u[1], best[f"{u[0]}.{u[1]}"]) for u in unknowns])
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
        predicted_dbm={"before": before, "after": after}, holdout_mask=held,
        cost={"traces": model.solves, "field_evaluations": model.field_evaluations})
