"""Every use of Sionna RT's private internals, in one place (Sionna SYS's: its sibling).

**Sionna RT.** The shoot cache (:mod:`caviar_plugins.rt.shoot_cache`) splits Sionna's
candidate generator (``SBCandidateGenerator``) in two phases and the path-buffer watch of
:class:`~caviar_plugins.rt.solver.PathTracer` reads its per-source candidate counter.
Both need names Sionna does not document: the solver's ``_candidate_generator``, the
generator's ``_los``, ``_sampler``, ``_sample_radio_material`` and hashers, the path
buffer and the sample-data fields, and the positional order of some arguments; adding
the moving boxes' Doppler shifts writes ``Paths._doppler``.

**Sionna SYS.** Its internals, and PyTorch's that the link level uses, are
:mod:`caviar_plugins.radio.sionna_sys_adapter`'s.

**Sionna's random state.** A draw that takes no generator (a 38.901 drop, large-scale
parameters) runs under :func:`seeded`, which puts ``sionna.phy.config``'s generators back
afterwards: no global seed stays set.

Nothing else in this project but that module touches a private name of Sionna
(``tests/test_sionna_adapter.py`` checks it with an allowlist). :func:`problem` checks, on first
use, that the installed sionna-rt is the minor version this code was written and tested for
(:data:`TESTED_VERSION`) and that every name it uses exists with the arguments it passes:
``None`` when all is well, otherwise a sentence saying what is missing; :func:`require`
raises :class:`SionnaInternalsError` with it. The path tracer then warns and runs Sionna's
own loop (no shoot cache, no path-buffer overflow report): slower, never wrong.
"""

from __future__ import annotations

import contextlib
import inspect
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from caviar_plugins.rt.drjit_setup import configure_drjit

TESTED_VERSION = (2, 2)
"""The sionna-rt minor version the shoot cache was checked against (tests/test_shoot_cache.py);
plugins/pyproject.toml pins the ``radio`` extra to it."""


class SionnaInternalsError(RuntimeError):
    """The installed Sionna RT lacks an internal this project uses."""


# (module, attribute path, for what): every private or undocumented name used here.
_NEEDED = (
    ("sionna.rt.path_solvers.path_solver", "PathSolver", "the solver"),
    ("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator._los", "line-of-sight candidates"),
    ("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator._shoot_and_bounce",
     "the path-buffer watch"),
    ("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator._sample_radio_material",
     "the shoot phase"),
    ("sionna.rt.path_solvers.paths_buffer", "PathsBuffer.add_paths", "storing connected paths"),
    ("sionna.rt.path_solvers.paths_buffer", "PathsBuffer.schedule", "storing connected paths"),
    ("sionna.rt.path_solvers.paths_buffer", "PathsBuffer.paths_counter", "storing connected paths"),
    ("sionna.rt.path_solvers.sample_data", "SampleData.SampleDataFields", "the shoot phase's sample data"),
    ("sionna.rt.path_solvers.sample_data", "source_index_per_sample", "the shoot phase"),
    ("sionna.rt.path_solvers.paths_buffer", "PathsBuffer.shrink", "paths traced once, their fields many times"),
    ("sionna.rt.path_solvers.paths_buffer", "PathsBuffer.detach_geometry",
     "paths traced once, their fields many times"),
    ("sionna.rt.constants", "InteractionType", "interaction flags"),
    ("sionna.rt.utils", "WedgeGeometry", "diffraction"),
    ("sionna.rt.utils", "fibonacci_lattice", "the rays' directions"),
    ("sionna.rt.utils", "hash_fnv1a", "chain hashes"),
    ("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator.MIN_SPEC_COUNT_SIZE",
     "the size of the specular-chain table"),
    ("sionna.rt.utils", "spawn_ray_from_sources", "the rays' origins"),
)
# Arguments passed by position: (method, parameter, its index among the positional ones after self).
_POSITIONAL = (
    ("_los", "paths_counter_per_source", 4),
    ("_shoot_and_bounce", "paths_counter_per_source", 7),
)
# Instance attributes of a fresh generator / solver.
_GENERATOR_ATTRIBUTES = ("_sampler", "plane_hash_functions", "edge_hash_functions")
_SOLVER_ATTRIBUTES = ("_candidate_generator", "_image_method", "_field_calculator")


def _resolve(module: str, path: str) -> Any:
    import importlib

    obj: Any = importlib.import_module(module)
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _check() -> str | None:
    """None when the installed Sionna RT has everything used here, else what is wrong."""
    configure_drjit()
    try:
        import sionna.rt as rt
    except ImportError as e:
        return f"sionna-rt cannot be imported ({e})"
    version = str(getattr(rt, "__version__", "unknown"))
    try:
        major_minor = tuple(int(x) for x in version.split(".")[:2])
    except ValueError:
        major_minor = ()
    tested = ".".join(map(str, TESTED_VERSION))
    if major_minor != TESTED_VERSION:
        return (f"sionna-rt {version} is installed; the shoot cache uses Sionna RT internals checked against "
                f"{tested}.x only (pip install 'sionna-rt>={tested},<{TESTED_VERSION[0]}.{TESTED_VERSION[1] + 1}')")
    for module, path, purpose in _NEEDED:
        try:
            _resolve(module, path)
        except (ImportError, AttributeError):
            return f"sionna-rt {version} has no {module}.{path} (used for {purpose})"
    generator_class = _resolve("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator")
    for method, parameter, index in _POSITIONAL:
        names = [p.name for p in inspect.signature(getattr(generator_class, method)).parameters.values()][1:]
        if len(names) <= index or names[index] != parameter:
            return (f"sionna-rt {version}: SBCandidateGenerator.{method} does not take {parameter!r} as "
                    f"positional argument {index}")
    return _check_instances(rt, version, generator_class)


def _check_instances(rt: Any, version: str, generator_class: Any) -> str | None:
    """A fresh solver's and generator's private attributes."""
    try:
        solver = rt.PathSolver()
    except Exception as e:  # noqa: BLE001 - any failure means the internals cannot be used
        return f"sionna-rt {version}: PathSolver() failed ({e})"
    for name in _SOLVER_ATTRIBUTES:
        if not hasattr(solver, name):
            return f"sionna-rt {version}: PathSolver has no attribute {name!r}"
    generator = getattr(solver, "_candidate_generator", None)
    if not isinstance(generator, generator_class):
        return f"sionna-rt {version}: PathSolver has no _candidate_generator of type SBCandidateGenerator"
    for name in _GENERATOR_ATTRIBUTES:
        if not hasattr(generator, name):
            return f"sionna-rt {version}: SBCandidateGenerator has no attribute {name!r}"
    return None


def problem() -> str | None:
    """None when the installed Sionna RT has every internal used here; otherwise why not.
    Checked once, on first use (it imports Sionna RT); kept as the module's ``PROBLEM``."""
    found = globals()
    if "PROBLEM" not in found:
        found["PROBLEM"] = _check()
    return found["PROBLEM"]


def __getattr__(name: str) -> Any:
    if name == "PROBLEM":
        return problem()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def require() -> None:
    """Raises :class:`SionnaInternalsError` naming what is missing, if anything is."""
    found = problem()
    if found is not None:
        raise SionnaInternalsError(found)


# --- the solver ------------------------------------------------------------------------------

def candidate_generator(solver: Any) -> Any:
    """The solver's shoot-and-bounce candidate generator."""
    require()
    return solver._candidate_generator


def replace_candidate_generator(solver: Any, generator: Any) -> None:
    """Makes ``solver`` call ``generator`` (same signature as Sionna's) for its candidates."""
    require()
    solver._candidate_generator = generator


def watch_candidate_counter(solver: Any, on_counter: Callable[[Any], None]) -> None:
    """Calls ``on_counter(counter)`` with the per-source candidate counter that Sionna's
    line-of-sight test and shoot-and-bounce increment for every candidate, before the
    ``max_num_paths_per_src`` cap (NVlabs/sionna#1172): read after a solve, a count above
    the cap is the number of candidates dropped."""
    generator = candidate_generator(solver)
    for name, _, index in _POSITIONAL:
        method = getattr(generator, name)

        def spy(*args, _method=method, _index=index, **kwargs):
            on_counter(kwargs.get("paths_counter_per_source", args[_index] if len(args) > _index else None))
            return _method(*args, **kwargs)

        setattr(generator, name, spy)


def set_doppler(paths: Any, doppler) -> None:
    """Replaces the Doppler shifts (Hz) of Sionna's ``Paths`` (its private ``_doppler``, of
    the shape ``paths.doppler`` has): for velocities Sionna cannot see (boxes of one mesh
    moving each with its own, :class:`~caviar_plugins.rt.scatterers.ScattererPool`)."""
    import drjit as dr
    import mitsuba as mi

    if not hasattr(paths, "_doppler"):
        raise SionnaInternalsError("sionna-rt's Paths has no _doppler: the moving boxes' Doppler shifts cannot be "
                                   f"added (checked against sionna-rt {'.'.join(map(str, TESTED_VERSION))})")
    doppler = np.asarray(doppler, dtype=np.float32)
    paths._doppler = dr.reshape(mi.TensorXf, mi.Float(doppler.ravel().tolist()), doppler.shape)


# --- Sionna's table of specular chains seen --------------------------------------------------
#
# Sionna's shoot-and-bounce marks a (specular chain, target) pair as seen in two tables of
# max(max_num_paths_per_src, MIN_SPEC_COUNT_SIZE = 1e6) counters per source, indexed by two
# hashes modulo that size, and drops a new pair whose slot in either table another pair took,
# silently. To first order the share so dropped is the tables' load: the pairs found per
# source over the slots (each target a chain sees is a pair). 500 receivers and 2e5 rays on
# osm-city make about 280,000 pairs: 23 % were lost, and which ones depended on the other
# receivers traced with them (up to 19 dB on one receiver's power). The tracer therefore
# checks the load after a solve and solves again with a larger table where it is above
# :data:`CHAIN_LOSS` (:func:`chain_table_slots`).

CHAIN_LOSS = 0.01
"""The share of specular chains a solve may lose to hash collisions (the tables' load)."""
MAX_CHAIN_SLOTS = 1 << 26
"""The most slots per source a table is grown to (two tables of 4-byte counters: 512 MiB a
source)."""


def chain_table_size(max_num_paths_per_src: int, slots: int = 0) -> int:
    """The slots per source Sionna's specular-chain tables have in a solve with
    ``max_num_paths_per_src`` under :func:`chain_table` (``slots``; 0: Sionna's own floor)."""
    require()
    generator_class = _resolve("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator")
    return max(int(max_num_paths_per_src), int(slots) or int(generator_class.MIN_SPEC_COUNT_SIZE))


def chain_loss(pairs_per_source: int, slots: int) -> float:
    """The share of new specular chains dropped by collisions, to first order (the load of
    the tables), with ``pairs_per_source`` candidates found in tables of ``slots``. The
    candidates counted include line-of-sight and diffuse ones, which take no slot: an upper
    bound where diffuse reflection finds many (a table grown larger than it need be)."""
    return float(pairs_per_source) / float(slots)


def chain_table_slots(pairs_per_source: int, sources: int = 1) -> int:
    """Slots per source that bring the loss of ``pairs_per_source`` candidates to a tenth of
    :data:`CHAIN_LOSS` (room for the ones a smaller table lost), at most
    :data:`MAX_CHAIN_SLOTS` and 2**27 over all ``sources`` (1 GiB)."""
    want = int(math.ceil(10.0 * pairs_per_source / CHAIN_LOSS))
    return max(1, min(want, MAX_CHAIN_SLOTS, (1 << 27) // max(int(sources), 1)))


def chain_table_check(found_per_source: int, max_num_paths_per_src: int, slots: int, sources: int
                      ) -> tuple[float, int, int]:
    """After a solve under :func:`chain_table` (``slots``) that found ``found_per_source``
    candidates a source (the most of any of ``sources``): the share lost to collisions
    (:func:`chain_loss`), the slots the tables had, and the slots to solve again with (0: none,
    the loss being within :data:`CHAIN_LOSS` or the table at its cap: :func:`chain_loss_warning`)."""
    size = chain_table_size(max_num_paths_per_src, slots)
    loss = chain_loss(found_per_source, size)
    grown = chain_table_slots(found_per_source, sources)
    return loss, size, (grown if loss > CHAIN_LOSS and grown > size else 0)


def chain_loss_warning(loss: float, size: int, advice: str) -> str:
    """What a tracer warns when its table, at its cap, still loses ``loss`` of the chains."""
    return (f"about {100 * loss:.0f} % of the specular chains are lost to collisions in Sionna's table of chains "
            f"seen ({size} slots a source, the most allowed): {advice}")


@contextlib.contextmanager
def chain_table(slots: int) -> Iterator[None]:
    """Solves inside get specular-chain tables of ``slots`` per source (or
    ``max_num_paths_per_src`` where larger; 0: Sionna's own 1e6): Sionna reads the size from
    a class constant, put back afterwards (so not for solves in two threads at once: none
    here solves from more than one thread)."""
    if not slots:
        yield
        return
    require()
    generator_class = _resolve("sionna.rt.path_solvers.sb_candidate_generator", "SBCandidateGenerator")
    before = generator_class.MIN_SPEC_COUNT_SIZE
    generator_class.MIN_SPEC_COUNT_SIZE = int(slots)
    try:
        yield
    finally:
        generator_class.MIN_SPEC_COUNT_SIZE = before


# --- paths traced once, their fields computed many times (a fit of the materials) -----------

class TracedGeometry:
    """What :func:`trace_geometry` keeps of one solve: Sionna's path buffer with the paths'
    geometry (detached: it does not depend on the materials), the sources' and targets'
    positions, orientations and antenna patterns, and the paths' validity before any field
    was computed."""

    def __init__(self, buffer: Any, valid: Any, samples_per_src: int, diffraction: bool, frame: tuple):
        self.buffer, self.valid, self.samples_per_src, self.diffraction = buffer, valid, samples_per_src, diffraction
        self.frame = frame

    @property
    def num_paths(self) -> int:
        return int(self.buffer.buffer_size)

    @property
    def source_indices(self) -> Any:
        return self.buffer.source_indices

    @property
    def target_indices(self) -> Any:
        return self.buffer.target_indices


def trace_geometry(solver: Any, scene: Any, *, max_num_paths_per_src: int, samples_per_src: int, max_depth: int,
                   los: bool, specular_reflection: bool, diffuse_reflection: bool, refraction: bool,
                   diffraction: bool, edge_diffraction: bool = False, diffraction_lit_region: bool = True,
                   seed: int = 42) -> TracedGeometry:
    """The first half of ``PathSolver.__call__`` (sionna-rt 2.2, ``synthetic_array = True``):
    candidates and the image method, not the fields. Valid for any material values as long as
    the paths' geometry does not depend on them: with diffuse reflection off (Sionna samples a
    diffuse bounce with a probability the scattering coefficient sets)."""
    import drjit as dr

    require()
    scene.all_set(radio_map=False)
    src_positions, src_orientations, _, _ = scene.sources(True, True)
    tgt_positions, tgt_orientations, _, _ = scene.targets(True, True)
    dr.make_opaque(src_positions, tgt_positions, src_orientations, tgt_orientations)
    buffer = solver._candidate_generator(
        mi_scene=scene.mi_scene, src_positions=src_positions, tgt_positions=tgt_positions,
        samples_per_src=samples_per_src, max_num_paths_per_src=max_num_paths_per_src, max_depth=max_depth, los=los,
        specular_reflection=specular_reflection, diffuse_reflection=diffuse_reflection, refraction=refraction,
        diffraction=diffraction, edge_diffraction=edge_diffraction, seed=seed)
    buffer.schedule()
    dr.eval()
    buffer.shrink()
    buffer.detach_geometry()
    buffer = solver._image_method(scene=scene.mi_scene, paths=buffer, src_positions=src_positions,
                                  tgt_positions=tgt_positions, diffraction=diffraction,
                                  diffraction_lit_region=diffraction_lit_region)
    frame = (src_positions, tgt_positions, src_orientations, tgt_orientations,
             scene.tx_array.antenna_pattern.patterns, scene.rx_array.antenna_pattern.patterns)
    valid = dr.copy(buffer.valid) if buffer.buffer_size else buffer.valid
    dr.eval(valid)
    return TracedGeometry(buffer, valid, samples_per_src, diffraction, frame)


def path_powers(solver: Any, scene: Any, traced: TracedGeometry) -> Any:
    """Each traced path's power Σ|a|² averaged over the pairs of antenna patterns (a Dr.Jit
    ``Float``, 0 for an invalid path), with the scene's materials as they are now: the second
    half of ``PathSolver.__call__`` (the field calculator, in ``solver``'s loop mode, so that
    gradients flow to the materials when it is "evaluated")."""
    import drjit as dr
    import mitsuba as mi

    require()
    buffer = traced.buffer
    if traced.num_paths == 0:
        return dr.zeros(mi.Float, 0)
    buffer.valid = dr.copy(traced.valid)  # the calculator narrows it to the paths with a field
    src_positions, tgt_positions, src_orientations, tgt_orientations, src_patterns, tgt_patterns = traced.frame
    buffer = solver._field_calculator(
        wavelength=scene.wavelength, paths=buffer, samples_per_src=traced.samples_per_src,
        diffraction=traced.diffraction, src_positions=src_positions, tgt_positions=tgt_positions,
        src_orientations=src_orientations, tgt_orientations=tgt_orientations,
        src_antenna_patterns=src_patterns, tgt_antenna_patterns=tgt_patterns)
    power = dr.zeros(mi.Float, traced.num_paths)
    count = 0
    for row in buffer.a:
        for a in row:
            power += dr.square(dr.real(a)) + dr.square(dr.imag(a))
            count += 1
    return dr.select(buffer.valid, power / count, 0.0)


def path_delays(traced: TracedGeometry) -> np.ndarray:
    """Each traced path's delay (s), as the last :func:`path_powers` computed it (the field
    calculator sets the buffer's ``tau``; a path's delay depends on its geometry only)."""
    require()
    tau = getattr(traced.buffer, "tau", None)
    if tau is None:
        raise SionnaInternalsError("no path delays: path_powers has not run on these paths")
    return np.array(tau, dtype=np.float64).reshape(-1)


# --- the generator's parts (the shoot cache) -------------------------------------------------

def add_line_of_sight(generator: Any, mi_scene, src_positions, tgt_positions, paths, counter) -> None:
    """Sionna's line-of-sight candidates into ``paths``."""
    generator._los(mi_scene, src_positions, tgt_positions, paths, counter, None)


def sampler(generator: Any) -> Any:
    """The generator's random sampler (Mitsuba's ``independent``)."""
    return generator._sampler


def sample_radio_material(generator: Any, *args) -> Any:
    """Sionna's interaction sampling at a hit: (sample, oriented normal, wedges)."""
    return generator._sample_radio_material(*args)


def hashers(generator: Any) -> tuple[list, list]:
    """The generator's plane and edge hash functions (two each: round, floor)."""
    return generator.plane_hash_functions, generator.edge_hash_functions


def new_paths_buffer(size: int, max_depth: int, diffraction: bool) -> Any:
    from sionna.rt.path_solvers.paths_buffer import PathsBuffer

    return PathsBuffer(size, max_depth, diffraction)


def sample_data_fields() -> Any:
    """``SampleData.SampleDataFields``: (interaction type, shape, primitive, vertex, probability)."""
    from sionna.rt.path_solvers.sample_data import SampleData

    return SampleData.SampleDataFields


def source_index_per_sample(num_sources: int, samples_per_src: int) -> Any:
    from sionna.rt.path_solvers.sample_data import source_index_per_sample as f

    return f(num_sources, samples_per_src)


def ray_utilities() -> tuple[Any, Any, Any, Any, Any]:
    """(InteractionType, WedgeGeometry, fibonacci_lattice, hash_fnv1a, spawn_ray_from_sources)."""
    from sionna.rt.constants import InteractionType
    from sionna.rt.utils import WedgeGeometry, fibonacci_lattice, hash_fnv1a, spawn_ray_from_sources

    return InteractionType, WedgeGeometry, fibonacci_lattice, hash_fnv1a, spawn_ray_from_sources


# --- Sionna's random state ------------------------------------------------------------------

@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Sionna's random state seeded with ``seed`` while the block runs (for its draws that
    take no generator, such as a 38.901 topology or large-scale parameters), and put back
    afterwards as it was: Sionna's own generators (``sionna.phy.config``'s ``_seed``,
    ``_py_rng``, ``_np_rng``, ``_torch_rngs``, which its seed setter replaces) and torch's
    default generators, which the setter reseeds too. Another user of Sionna's random state
    (the link level's block errors) goes on as if the block had not run."""
    import torch
    from sionna.phy import config

    saved = (config._seed, config._py_rng, config._np_rng, config._torch_rngs)
    cpu = torch.default_generator.get_state()
    gpus = [g.get_state() for g in torch.cuda.default_generators] if torch.cuda.is_available() else []
    config.seed = int(seed) % 2**31
    try:
        yield
    finally:
        config._seed, config._py_rng, config._np_rng, config._torch_rngs = saved
        torch.default_generator.set_state(cpu)
        for g, state in zip(torch.cuda.default_generators, gpus, strict=True):
            g.set_state(state)
