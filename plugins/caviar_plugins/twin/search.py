"""The search and the descents of a material fit (:mod:`caviar_plugins.twin.fit`): the
coordinates a fit moves in (logarithms that keep each property physical), the coarse search
over a property's range, Levenberg–Marquardt and Adam, restarts from random values, descents
from the rival values the search found, a joint grid over a confounded pair, and the
likelihood-ratio test for a property left out. Each
works on a fit's problem (the measurements placed in the scene, predictions at given logs)
and appends its evaluations to the fit's history."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from caviar_plugins.rt.received_power import Unknown

Problem = Any
"""A fit's problem (``caviar_plugins.twin.fit._Problem``: ``unknowns``, ``data``, ``model``,
``pairs``, ``frozen``, ``values``, ``predict``, ``jacobian``); typed loosely, since the fit
imports this module."""
Settings = Any
"""A fit's settings (``caviar_plugins.twin.fit.FitSettings``)."""

LOWER = {"relative_permittivity": 1.0 + 1e-3, "conductivity": 1e-6, "scattering_coefficient": 1e-4}
SEARCH_RANGE = {"relative_permittivity": (1.5, 80.0), "conductivity": (1e-3, 10.0),
                "scattering_coefficient": (0.01, 0.9)}
"""Where the coarse search looks for each property (the span of ITU-R P.2040's materials)."""
JACOBIAN_STEP = 0.01
"""The central difference's step in a property's log for the Levenberg–Marquardt Jacobian."""
MAX_LOG_STEP = 0.3
"""A Levenberg–Marquardt step moves no log by more than this (about ±35 %)."""

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



def rmse(pred: np.ndarray, measured: np.ndarray, mask: np.ndarray) -> float:
    m = mask & np.isfinite(pred)
    return float(np.sqrt(np.mean((pred[m] - measured[m]) ** 2))) if m.any() else float("nan")


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


def add_rival(ambiguous: dict[Unknown, list[float]], u: Unknown, value: float, tol: float) -> None:
    """Lists ``value`` among ``u``'s rivals unless one within ``tol`` in its log is there."""
    rivals = ambiguous.setdefault(u, [])
    if all(abs(to_log(u[1], v) - to_log(u[1], value)) > tol for v in rivals):
        rivals.append(value)


def record(problem: Problem, x: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
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


def coarse_search(problem: Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                  settings: Settings, history: list[dict[str, Any]],
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
            err = record(problem, trial, fit_mask, held, history, progress, None, phase="search", **label)
            profile.append(n_fit * err**2 if np.isfinite(err) else np.inf)
            if err < best:
                best, x = err, trial
        found = rival_minima(grid, np.array(profile), 3.84 * settings.noise_db**2)
        if found:
            rivals[problem.unknowns[k]] = found
    return x, rivals


def _iteration(history: list[dict[str, Any]]) -> int:
    return sum(r["phase"] == "descent" for r in history)


def _plateaued(history: list[dict[str, Any]], settings: Settings, since: int) -> bool:
    errs = [r["fit_rmse_db"] ** 2 for r in history[since:] if r["phase"] == "descent"]
    return len(errs) > settings.patience and errs[-1 - settings.patience] - errs[-1] < settings.plateau * errs[
        -1 - settings.patience]


def levenberg_marquardt(problem: Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray,
                        held: np.ndarray, settings: Settings, history: list[dict[str, Any]],
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
    err = record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
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
        record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
                iteration=_iteration(history))
    return x, f"{settings.iterations} iterations"


def adam(problem: Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
         settings: Settings, history: list[dict[str, Any]],
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
        record(problem, x, fit_mask, held, history, progress, pred=pred, phase="descent",
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


def descent(settings: Settings) -> Callable[..., tuple[np.ndarray, str]]:
    """The descent ``settings.method`` names: :func:`levenberg_marquardt` or :func:`adam`."""
    return levenberg_marquardt if settings.method == "lm" else adam


def restart_rounds(problem: Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                   settings: Settings, history: list[dict[str, Any]],
                   progress: Callable[[dict[str, Any]], None] | None, ident: Any
                   ) -> tuple[np.ndarray, list[np.ndarray]]:
    """``settings.restarts`` rounds from random values (see :attr:`~caviar_plugins.twin.fit.FitSettings.restarts`):
    returns the best logs and the rounds' distinct ends, best first; adds to
    ``ident.ambiguous`` the values of every other round's minimum that fits within the
    likelihood bound and lies outside the best's bound."""
    measured = problem.data.power_dbm
    rng = np.random.default_rng(settings.seed + 1)
    descend = descent(settings)
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
                add_rival(ident.ambiguous, u, from_log(u[1], float(other[k])), settings.max_log_std)
    problem.predict(best)
    return best, _distinct(minima, free, settings.max_log_std)


def _distinct(minima: list[tuple[float, np.ndarray]], free: np.ndarray, tol: float) -> list[np.ndarray]:
    """The minima's logs, best first, each differing from every better one by more than
    ``tol`` in some free unknown."""
    ends: list[np.ndarray] = []
    for e, other in sorted(minima, key=lambda m: m[0] if np.isfinite(m[0]) else np.inf):
        if np.isfinite(e) and all(np.max(np.abs(other - end)[free], initial=0.0) > tol for end in ends):
            ends.append(other)
    return ends


def _best_fitting(problem: Problem, x: np.ndarray, starts: list[tuple[int, float]], fit_mask: np.ndarray,
                  alone: dict[tuple[int, float], float]) -> tuple[int, float]:
    """Of ``starts`` (unknown, log), the one whose fit RMSE is lowest with the others at ``x``;
    ``alone`` keeps each one's RMSE (the caller clears it when ``x`` moves)."""
    for k, lv in starts:
        if (k, lv) not in alone:
            trial = x.copy()
            trial[k] = lv
            e = rmse(problem.predict(trial), problem.data.power_dbm, fit_mask)
            alone[(k, lv)] = e if np.isfinite(e) else math.inf
    return min(starts, key=alone.__getitem__)


def _untried(problem: Problem, x: np.ndarray, free: np.ndarray, ambiguous: dict[Unknown, list[float]],
             tried: list[tuple[int, float]], tol: float) -> list[tuple[int, float]]:
    """The rivals of free unknowns, as (unknown, log), outside ``x``'s basin and not within
    ``tol`` of one already tried."""
    starts = [(k, to_log(u[1], v)) for k, u in enumerate(problem.unknowns) if free[k] for v in ambiguous.get(u, [])]
    return [(k, lv) for k, lv in starts if abs(lv - x[k]) > tol
            and all(k != j or abs(lv - lt) > tol for j, lt in tried)]


def rival_descents(problem: Problem, x: np.ndarray, free: np.ndarray, fit_mask: np.ndarray, held: np.ndarray,
                   settings: Settings, history: list[dict[str, Any]],
                   progress: Callable[[dict[str, Any]], None] | None, ambiguous: dict[Unknown, list[float]]
                   ) -> np.ndarray:
    """Descents from the rivals (see :attr:`~caviar_plugins.twin.fit.FitSettings.rival_starts`):
    a rival value of one property (another basin of its profile, or another round's minimum,
    that fit about as well with the others where they were) is where the others may have
    been set to make up for it. From each, the best-fitting first, that property set to the
    rival, a coarse sweep of the others, then a descent of all, then up to
    ``search_sweeps - 1`` rounds of a sweep of all and a descent while they find better; the
    end is kept if it fits better. A minimum so left that still fits within the likelihood bound becomes a
    rival in turn (in ``ambiguous``), and new rivals the sweeps find are tried too, up to
    ``settings.rival_starts`` descents in all."""
    measured = problem.data.power_dbm
    n_fit = int(fit_mask.sum())
    descend = descent(settings)
    err = rmse(problem.predict(x), measured, fit_mask)
    tried: list[tuple[int, float]] = []
    alone: dict[tuple[int, float], float] = {}  # each rival's fit with the others at x, until x moves
    for _ in range(settings.rival_starts):
        pending = _untried(problem, x, free, ambiguous, tried, settings.max_log_std)
        if not pending:
            break
        k, lv = _best_fitting(problem, x, pending, fit_mask, alone)
        tried.append((k, lv))
        trial = x.copy()
        trial[k] = lv
        others = free.copy()
        others[k] = False
        if settings.search_sweeps and others.any():
            trial, found = coarse_search(problem, trial, others, fit_mask, held, settings, history, progress, sweep=-3)
            for u, vs in found.items():
                for v in vs:
                    add_rival(ambiguous, u, v, settings.max_log_std)
        trial, _ = descend(problem, trial, free, fit_mask, held, settings, history, progress)
        trial_err = rmse(problem.predict(trial), measured, fit_mask)
        for _sweep in range(1, settings.search_sweeps):  # the others may now sit in a wrong basin in turn
            again, _ = coarse_search(problem, trial, free, fit_mask, held, settings, history, progress, sweep=-3)
            again, _ = descend(problem, again, free, fit_mask, held, settings, history, progress)
            again_err = rmse(problem.predict(again), measured, fit_mask)
            if not again_err < trial_err * (1 - settings.plateau):
                break
            trial, trial_err = again, again_err
        if np.isfinite(trial_err) and trial_err < err:
            if n_fit * (err**2 - trial_err**2) <= 3.84 * settings.noise_db**2:  # the one left fits as well
                for j in np.flatnonzero(free):
                    if abs(x[j] - trial[j]) > settings.max_log_std:
                        u = problem.unknowns[j]
                        add_rival(ambiguous, u, from_log(u[1], float(x[j])), settings.max_log_std)
            x, err = trial, trial_err
            alone.clear()
    problem.predict(x)
    return x


PAIR_POINTS = 40
"""Values per property of the joint grid over a confounded pair (:func:`pair_search`)."""


def pair_search(problem: Problem, x: np.ndarray, i: int, k: int, fit_mask: np.ndarray, held: np.ndarray,
                history: list[dict[str, Any]], progress: Callable[[dict[str, Any]], None] | None,
                keep: int = 3) -> list[np.ndarray]:
    """A joint grid of :data:`PAIR_POINTS` × :data:`PAIR_POINTS` values over unknowns ``i``
    and ``k`` (the others held): the ``keep`` best points, from which descents start."""
    ui, uk = problem.unknowns[i][1], problem.unknowns[k][1]
    scored = []
    for vi in search_grid(ui, PAIR_POINTS):
        for vk in search_grid(uk, PAIR_POINTS):
            trial = x.copy()
            trial[i], trial[k] = to_log(ui, float(vi)), to_log(uk, float(vk))
            err = record(problem, trial, fit_mask, held, history, progress, None, phase="search", sweep=-2)
            scored.append((err if np.isfinite(err) else math.inf, trial))
    scored.sort(key=lambda e: e[0])
    return [t for _, t in scored[:keep]]


def likelihood_ratio_inclusion(problem: Problem, x: np.ndarray, free: np.ndarray, start: dict[Unknown, float],
                               fit_mask: np.ndarray, held: np.ndarray, settings: Settings,
                               history: list[dict[str, Any]], progress: Callable[[dict[str, Any]], None] | None,
                               confounded: Mapping[Unknown, list[Unknown]] | None = None,
                               origins: list[np.ndarray] | None = None) -> tuple[np.ndarray, list[Unknown]]:
    """The global check the local bound cannot make: for each property left at its start, a
    search over it and a descent of it with the learned ones; if that lowers the fit samples'
    Σ err² by more than a likelihood-ratio test at 95 % allows (3.84·noise_db²), the data do
    see it (a ground's conductivity, whose effect its permittivity mimics near the start but
    not over the whole flight): it is learned from then on (``free`` is updated). Returns the
    logs and the properties so learned. A property a learned one is ``confounded`` with is
    searched jointly with it (:func:`pair_search`): alone, its grid holds the partner at the
    value that made up for it. The test starts from ``x`` and from each of ``origins`` (other
    minima the rounds ended at): a property left at a wrong value makes the learned ones make up
    for it, and the minimum that fits best with it wrong need not be the one nearest the truth."""
    confounded = confounded or {}
    measured = problem.data.power_dbm
    n_fit = int(fit_mask.sum())
    descend = descent(settings)
    err = rmse(problem.predict(x), measured, fit_mask)
    seen: list[Unknown] = []
    for k in [int(k) for k in np.flatnonzero(~free)]:
        u = problem.unknowns[k]
        trial_free = free.copy()
        trial_free[k] = True
        problem.frozen = {v: start[v] for v, f in zip(problem.unknowns, trial_free, strict=True) if not f}
        partners = [j for j, v in enumerate(problem.unknowns) if u in confounded.get(v, [])]
        starts = []
        for origin in [x, *(origins or [])]:
            origin = np.where(free, origin, x)  # what is still frozen stays at its start
            if partners:  # a joint grid over the pair whose effects look alike, then descents from its best cells
                starts += pair_search(problem, origin, partners[0], k, fit_mask, held, history, progress)
            else:
                only = np.zeros_like(free)
                only[k] = True
                starts.append(coarse_search(problem, origin, only, fit_mask, held, settings, history, progress,
                                            sweep=-1)[0])
        trial, trial_err = x, math.inf
        for begin in starts:
            end, _ = descend(problem, begin, trial_free, fit_mask, held, settings, history, progress)
            end_err = rmse(problem.predict(end), measured, fit_mask)
            if end_err < trial_err:
                trial, trial_err = end, end_err
        if np.isfinite(trial_err) and n_fit * (err**2 - trial_err**2) > 3.84 * settings.noise_db**2:
            x, err, free[k] = trial, trial_err, True
            seen.append(u)
    problem.frozen = {v: start[v] for v, f in zip(problem.unknowns, free, strict=True) if not f}
    problem.predict(x)
    return x, seen
