"""How rays are traced: :class:`TraceSettings`, the one settings table of every module that
traces rays (``raytracing = { … }`` in its parameters), and what Sionna RT's solvers are
called with from it (:meth:`TraceSettings.path_options`, :meth:`TraceSettings.map_options`).

A module chooses its own defaults (the SAR link traces 1e6 rays to depth 5 with every
interaction; the network's site tracer 1e5 to depth 3, specular and diffraction only), and a
configuration that gives some keys of the table keeps the module's defaults for the others
(:func:`caviar.check_params` starts a table from its field's default).
"""

from __future__ import annotations

import dataclasses
from typing import Any

DEFAULT_MAX_PATHS_PER_SOURCE = 1_000_000
"""Sionna's own default for ``max_num_paths_per_src``."""
INTERACTIONS = ("los", "specular_reflection", "diffuse_reflection", "refraction", "diffraction")
"""The interaction flags of Sionna RT's solvers, as :class:`TraceSettings` names them."""


def check_shoot_cache(value: bool | str, key: str = "shoot_cache") -> bool | str:
    """``value`` if it is a shoot-cache setting (true, false or ``"auto"``), else a
    ValueError naming ``key``."""
    if isinstance(value, bool) or value == "auto":
        return value
    raise ValueError(f'{key}: expected true, false or "auto", got {value!r}')


@dataclasses.dataclass(frozen=True)
class TraceSettings:
    """The rays a module traces, and how (``raytracing = { … }``)."""

    samples_per_src: int = 1_000_000
    """Rays shot from each source (Sionna's ``samples_per_src``; the radio map's
    ``samples_per_tx``)."""
    max_depth: int = 5
    """Interactions a path may have at most (0: the line of sight only)."""
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = True
    """Diffuse reflection (scattering) off the materials' ``scattering_coefficient``."""
    refraction: bool = True
    diffraction: bool = True
    seed: int | None = None
    """The solver's seed; None: the run's (``[episode] seed``)."""
    threads: int = 0
    """Dr.Jit CPU threads; 0 = all cores. On the CPU the solver's parallel sums differ in the
    last float bits from run to run; ``threads = 1`` makes runs bit-identical (measured 1.9x
    slower per solve on the 2-core development machine)."""
    shoot_cache: bool | str = "auto"
    """Keep the rays' bounces of a solve and, while the geometry stays the same, trace only
    the receivers' visibility tests in later solves
    (:class:`~caviar_plugins.rt.solver.PathTracer`, :mod:`~caviar_plugins.rt.shoot_cache`):
    0.08x of Sionna's loop for 1 receiver, 0.36x for 10 (1e6 samples, 2 cores). It covers one
    source per solve. ``false``: always Sionna's loop; ``"auto"`` (default): on for Dr.Jit's
    LLVM backend (the CPU), off on CUDA, where it measured slower than Sionna's loop
    (:func:`~caviar_plugins.rt.solver.use_shoot_cache`)."""
    max_num_paths_per_src: int = DEFAULT_MAX_PATHS_PER_SOURCE
    """Sionna's candidate-path buffer per source (its default). Candidates beyond it are
    dropped silently by Sionna (NVlabs/sionna#1172); the tracer detects it, warns and
    reports the number dropped. It also sizes Sionna's table of the specular chains seen (at
    least 1e6 slots), where a chain whose hash collides is dropped silently: the tracer grows
    that table for a solve that found too many candidates for it
    (:func:`~caviar_plugins.rt.sionna_adapter.chain_table_slots`)."""

    def __post_init__(self):
        for key in ("samples_per_src", "max_num_paths_per_src"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{key}: expected a whole number >= 1, got {v!r}")
        for key in ("max_depth", "threads"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{key}: expected a whole number >= 0{' (0: all cores)' if key == 'threads' else ''}"
                                 f", got {v!r}")
        for key in INTERACTIONS:
            if not isinstance(getattr(self, key), bool):
                raise ValueError(f"{key}: expected true or false, got {getattr(self, key)!r}")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise ValueError(f"seed: expected a whole number (or no key: the run's seed), got {self.seed!r}")
        check_shoot_cache(self.shoot_cache)

    def solver_seed(self, run_seed: int) -> int:
        """The seed the solvers get: :attr:`seed`, else the run's, in Sionna's range."""
        return int(run_seed if self.seed is None else self.seed) % (2**31)

    def interactions(self) -> dict[str, bool]:
        """The interaction flags, as Sionna's solvers name them."""
        return {key: bool(getattr(self, key)) for key in INTERACTIONS}

    def path_options(self, run_seed: int) -> dict[str, Any]:
        """The keywords of Sionna RT's ``PathSolver`` (but the buffer, which the tracer holds)."""
        return {"max_depth": self.max_depth, "samples_per_src": self.samples_per_src, **self.interactions(),
                "seed": self.solver_seed(run_seed)}

    def map_options(self, run_seed: int) -> dict[str, Any]:
        """The keywords of Sionna RT's ``RadioMapSolver``."""
        return {"max_depth": self.max_depth, "samples_per_tx": self.samples_per_src, **self.interactions(),
                "seed": self.solver_seed(run_seed)}


MOVED_TO_RAYTRACING = tuple(f.name for f in dataclasses.fields(TraceSettings))
"""The keys a plugin's parameters once had flat and now has in ``raytracing = { … }``: a
configuration that still writes one flat gets an error naming the new key."""


def moved_keys(*names: str, table: str = "raytracing") -> dict[str, str]:
    """``{old flat key: its new key}`` for ``Params.moved`` (see :func:`caviar.check_params`)."""
    return {name: f"{table}.{name}" for name in (names or MOVED_TO_RAYTRACING)}


def with_raytracing(cls: Any, **values: Any) -> Any:
    """``cls(**values)`` for a parameters dataclass with a ``raytracing`` table, where the
    keys of :class:`TraceSettings` among ``values`` may be given flat (for Python code and
    scripts): they go into the table, which keeps ``cls``'s own defaults (or the given
    ``raytracing``'s values) for the others."""
    rays = {key: values.pop(key) for key in list(values) if key in MOVED_TO_RAYTRACING}
    base = values.pop("raytracing", None)
    if base is None:
        field = next(f for f in dataclasses.fields(cls) if f.name == "raytracing")
        base = field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default
    return cls(**values, raytracing=dataclasses.replace(base, **rays))
