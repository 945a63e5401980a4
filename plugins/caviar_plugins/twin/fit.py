"""Learning a scene's radio materials from measurements through Sionna RT (differentiable ray
tracing; the method of Hoydis et al., "Learning radio environments by differentiable ray
tracing", 2024).

:func:`fit_materials` takes a scene (loaded at the measurements' carrier), measurements
(:class:`~caviar_plugins.twin.measurements.Measurements`) and :class:`FitSettings`, and:

1. keeps a held-out share of the samples out of the fit (``holdout``, drawn with ``seed``);
2. asks which properties the fit samples can identify: the sensitivity of the predicted dBm to
   each property (a central difference in its log), and the Cramér–Rao bound of each one's
   log given ``noise_db`` of measurement noise. A property whose bound is wider than
   ``max_log_std`` (0.2: about ±20 %), alone or because another one explains the same data,
   is not learned and is reported as not identifiable;
3. traces the measured places once: each guess computes only the fields along the found paths
   (:class:`~caviar_plugins.rt.received_power.ReceivedPower`);
4. searches each identifiable property over its physical range, the others held, and
   descends from the best (Levenberg–Marquardt, or Adam on Dr.Jit's gradient), in rounds; then
   restarts from random values (a wall's reflection oscillates with its permittivity, so the
   error has many narrow minima, and two walls can make up for each other); the search and
   the descents are :mod:`caviar_plugins.twin.search`;
5. takes the bound again at the solution, and tests each property left out by a
   likelihood-ratio test; reports a learned property that makes up for a fixed one as
   confounded, and other minima that fit as well as ambiguous;
6. reports the RMSE in dB before and after on the fit and the held-out samples (the honest
   figure), and the learned values beside the starting ones; with power-delay profiles among
   the measurements, the RMS error of the predicted delay spread too (never descended on).
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
from caviar_plugins.twin.search import (
    coarse_search,
    descent,
    from_log,
    likelihood_ratio_inclusion,
    record,
    restart_rounds,
    rival_descents,
    rmse,
    to_log,
)

FIT_RAYS = TraceSettings(samples_per_src=200_000, max_depth=3, diffuse_reflection=False, refraction=False,
                         diffraction=False, shoot_cache=False)
"""How a fit traces by default: 2e5 rays to depth 3, line of sight and specular reflections
(what received power at street level is made of; add diffraction or diffuse reflection with
``raytracing``: diffuse reflection is what makes a scattering coefficient identifiable)."""
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
    """Values per property in the coarse search (:func:`~caviar_plugins.twin.search.search_grid`). The permittivity's
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
    :data:`~caviar_plugins.twin.search.SEARCH_RANGE` with ``seed``), each a search sweep and a descent: two properties
    that trade off (a high permittivity on one wall making up for a low one on another) hold
    a coordinate search in a wrong pair of basins, which a start elsewhere leaves. The best
    round wins; another round's minimum that fits as well within the noise (the likelihood
    bound of :class:`Identifiability`) makes the values it differs in ambiguous."""

    inclusion_starts: int = 3
    """The likelihood-ratio test for a property left at its start
    (:func:`~caviar_plugins.twin.search.likelihood_ratio_inclusion`) starts from the fit's
    minimum and from this many of the next-best distinct minima its rounds ended at: with a
    ground's conductivity 5x too low, the walls and the ground's permittivity make up for it,
    and the minimum that does so best is not always the one from which freeing the
    conductivity finds the truth."""
    rival_starts: int = 8
    """Then at most this many descents from the rivals: a value of one property that another
    basin of its search profile, or another round's minimum, says fits about as well
    (:func:`~caviar_plugins.twin.search.rival_descents`). Each sets that property to the
    rival, sweeps the others and descends all; the best end wins. Coordinate searches and
    random rounds stop in a wrong pair of basins when two properties make up for each other
    (a wall's permittivity in its neighbouring basin, a street's raised to match): the truth
    is then among the rivals, and a descent from it finds the pair together."""

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
        for key, least in (("restarts", 0), ("rival_starts", 0), ("inclusion_starts", 0), ("search_sweeps", 0),
                           ("iterations", 1), ("patience", 1), ("search_points", 1)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < least:
                raise ValueError(f"{key}: expected a whole number >= {least}, got {v!r}")
        for key in ("learning_rate", "noise_db", "max_log_std", "plateau"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key}: expected a number > 0, got {v!r}")


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
                             "learned_from_the_data": (m, p) in self.learned, "identifiable": self.identified((m, p)),
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
    delay_spread_ns: dict[str, Any] = dataclasses.field(default_factory=dict)
    """With power-delay profiles among the measurements: the RMS error of the predicted RMS
    delay spread (ns), ``{"fit"|"held_out": {"before": ns, "after": ns}, "measured_median":
    ns, "samples": with a profile}`` (never descended on: a check of the multipath)."""
    delay_spread_s: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """``{"measured"|"before"|"after": RMS delay spread (s) per sample}`` (NaN: no profile)."""

    def as_json(self) -> dict[str, Any]:
        return {"learned": {f"{m}.{p}": {"start": self.start[(m, p)], "learned": self.learned[(m, p)]}
                            for (m, p) in self.start},
                "identifiability": self.identifiability.as_json(),
                "rmse_db": self.rmse_db, "samples": self.samples, "stopped": self.stopped,
                "iterations": sum(r["phase"] == "descent" for r in self.history) - 1,
                "search_evaluations": sum(r["phase"] == "search" for r in self.history), "groups": self.groups,
                "materials": {k: v.as_dict() for k, v in self.materials.items()}, "cost": self.cost,
                **({"delay_spread_ns": self.delay_spread_ns} if self.delay_spread_ns else {}),
                "history": self.history}


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

    def delay_spreads(self, x: np.ndarray) -> np.ndarray:
        """Each sample's predicted RMS delay spread (s) at ``x``, at the measurements'
        bandwidth's resolution."""
        return self.model.delay_spreads(self.pairs, 1.0 / self.data.bandwidth_hz, self.values(x))

    def jacobian(self, x: np.ndarray, step: float = 0.05, every: bool = False) -> np.ndarray:
        """d(predicted dBm)/d(log) per sample and unknown, by central differences; with
        ``every``, the held unknowns' columns too (as if none were held)."""
        frozen = self.frozen
        if every:
            self.frozen = {}
        try:
            return self._differences(x, step)
        finally:
            self.frozen = frozen

    def _differences(self, x: np.ndarray, step: float) -> np.ndarray:
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
        x, stopped = descent(settings)(problem, x, free, fit_mask, held, settings, history, progress)
        err = rmse(problem.predict(x), measured, fit_mask)
        if math.isfinite(last) and last - err <= settings.plateau * last:  # this round found nothing better
            break
        last = err
    if not free.any():
        record(problem, x, fit_mask, held, history, progress, phase="descent", iteration=0)
    else:
        x, ends = restart_rounds(problem, x, free, fit_mask, held, settings, history, progress, ident)
        x = rival_descents(problem, x, free, fit_mask, held, settings, history, progress, ident.ambiguous)
        # the bound at the estimate, where it belongs: a property that the start hid (a
        # ground's conductivity barely matters at a low permittivity) may show at the solution
        at_solution = identifiability(problem.jacobian(x, every=True), fit_mask, unknowns, settings)
        more = np.array([u in at_solution.identifiable for u in unknowns]) & ~free
        if more.any():
            free |= more
            problem.frozen = {u: start[u] for u, f in zip(unknowns, free, strict=True) if not f}
            x, stopped = descent(settings)(problem, x, free, fit_mask, held, settings, history, progress)
        x, seen = likelihood_ratio_inclusion(problem, x, free, start, fit_mask, held, settings, history, progress,
                                             at_solution.confounded, ends[1:1 + settings.inclusion_starts])
        if seen:
            stopped = f"{stopped}; then learned {', '.join(f'{m}.{p}' for m, p in seen)} (likelihood-ratio test)"
        if seen or more.any():  # the bound where the fit ended
            at_solution = identifiability(problem.jacobian(x, every=True), fit_mask, unknowns, settings)
        at_solution.learned = [u for u, f in zip(unknowns, free, strict=True) if f]
        at_solution.confounded = {u: fixed for u, fixed in
                                  ((u, [v for v in vs if v not in at_solution.learned])
                                   for u, vs in at_solution.confounded.items()) if fixed}
        at_solution.ambiguous = ident.ambiguous
        ident = at_solution
    # the best evaluation among those that kept every unlearned property at its start (a
    # likelihood-ratio trial that was not taken moved one)
    consistent = [r for r in history
                  if all(math.isclose(r[f"{m}.{p}"], v, rel_tol=1e-6) for (m, p), v in problem.frozen.items())]
    best = min(consistent, key=lambda r: r["fit_rmse_db"] if np.isfinite(r["fit_rmse_db"]) else np.inf,
               default=None)
    x_best = x if best is None else np.array([to_log(u[1], best[f"{u[0]}.{u[1]}"]) for u in unknowns])
    spreads = ({"measured": data.delay_spread_s(), "before": problem.delay_spreads(x0),
                "after": problem.delay_spreads(x_best)} if data.pdp is not None else {})
    after = problem.predict(x_best)
    learned = problem.values(x_best)
    ident.ambiguous = {u: rivals for u, rivals in  # a rival in the learned value's own basin is no rival
                       ((u, [v for v in vs if abs(to_log(u[1], v) - to_log(u[1], learned[u])) > settings.max_log_std])
                        for u, vs in ident.ambiguous.items()) if rivals}
    return FitResult(
        start=start, learned=learned, identifiability=ident,
        rmse_db={"fit": {"before": rmse(before, measured, fit_mask), "after": rmse(after, measured, fit_mask)},
                 "held_out": {"before": rmse(before, measured, held), "after": rmse(after, measured, held)}},
        history=history,
        samples={"total": n, "fit": int(fit_mask.sum()), "held_out": int(held.sum()),
                 "without_path": int((~np.isfinite(after)).sum())},
        stopped=stopped, materials=scene_materials(scene), groups=groups,
        predicted_dbm={"before": before, "after": after}, holdout_mask=held,
        cost={"traces": model.solves, "field_evaluations": model.field_evaluations},
        delay_spread_ns=_delay_spread_errors(spreads, fit_mask, held) if spreads else {}, delay_spread_s=spreads)


def _delay_spread_errors(spreads: dict[str, np.ndarray], fit_mask: np.ndarray, held: np.ndarray) -> dict[str, Any]:
    """The RMS error (ns) of the predicted delay spread at the start and the end over the
    samples with a profile (:attr:`FitResult.delay_spread_ns`)."""
    measured, before, after = spreads["measured"], spreads["before"], spreads["after"]

    def err(pred: np.ndarray, mask: np.ndarray) -> float | None:
        m = mask & np.isfinite(measured) & np.isfinite(pred)
        return round(float(np.sqrt(np.mean((pred[m] - measured[m]) ** 2))) * 1e9, 3) if m.any() else None

    return {"fit": {"before": err(before, fit_mask), "after": err(after, fit_mask)},
            "held_out": {"before": err(before, held), "after": err(after, held)},
            "measured_median": round(float(np.nanmedian(measured)) * 1e9, 3),
            "samples": int(np.isfinite(measured).sum())}
