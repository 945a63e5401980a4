"""Shoot once, connect every step: Sionna RT's shoot-and-bounce split in two phases.

Sionna's candidate generator (``SBCandidateGenerator``) runs one loop: rays leave the
sources, hit the scene, sample an interaction (specular, diffuse, refraction,
diffraction) and bounce on, up to ``max_depth``; at every bounce each target is tested
for visibility from the hit point, which decides whether a path is stored (a diffuse
path ending there, or a new specular chain, deduplicated by hash). The first part, the
bounces, depends on the scene, the sources and the seed only; the second part on the
targets. A UAV flying through a static city changes only the targets.

:class:`ShootCache` stands in for the solver's candidate generator:

* **shoot** (once per geometry): the bounces, one wavefront per depth with Sionna's own
  material sampling, hashing and random numbers, keeping per depth the rays still alive
  (hit point, oriented normal, interaction flags, chain hashes) and the sample data the
  path buffer needs;
* **connect** (every solve): for each depth, every (target, live ray) pair at once:
  the visibility test, the specular-chain deduplication and the storing of paths, as
  in Sionna's inner loop, over the live rays only (Sionna's loop runs every ray of a
  packet until the last one dies).

The candidates are those Sionna finds (same rays, same hits, same tests); only the
order in which they land in the buffer differs (depth-major here, ray-major there), so
sums over paths differ in the last float bits, and where several rays find the same
specular chain another of them may be the one stored (the image method refines each
chain to the same path). ``tests/test_shoot_cache.py`` compares with Sionna's loop.

The cache is keyed on a fingerprint of the geometry (objects' positions, orientations,
scales and materials, the frequency, the sources and the solver settings). A
fingerprint seen for the first time is traced by Sionna's own generator; the shoot phase
is recorded when the same fingerprint comes back, so a scene whose objects move every
step costs nothing extra.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any


def _jit() -> tuple[Any, Any]:
    """Dr.Jit and Mitsuba, untyped: Dr.Jit's stubs do not know Mitsuba's array types."""
    import drjit
    import mitsuba

    return drjit, mitsuba


class ShootCache:
    """A drop-in for ``PathSolver._candidate_generator`` (see the module docstring).

    ``fingerprint()`` returns a hashable description of everything but the targets that
    the bounces depend on; :meth:`RadioScene` supplies one.
    """

    def __init__(self, generator: Any, fingerprint: Callable[[], Hashable]):
        self.generator = generator
        self.fingerprint = fingerprint
        self._seen: Hashable | None = None
        self._key: Hashable | None = None
        self._shots: _Shots | None = None
        self.paths_counter_per_source: Any = None
        """The per-source candidate counter of the last solve served from the cache
        (before the ``max_num_paths_per_src`` cap; None when Sionna's loop ran)."""
        self.shoots = 0
        """Shoot phases recorded (geometry changes that came back)."""
        self.connects = 0
        """Solves served from a recorded shoot phase."""

    def invalidate(self) -> None:
        self._seen = self._key = self._shots = None

    def __call__(self, mi_scene, src_positions, tgt_positions, samples_per_src: int, max_num_paths_per_src: int,
                 max_depth: int, los: bool, specular_reflection: bool, diffuse_reflection: bool, refraction: bool,
                 diffraction: bool, edge_diffraction: bool, seed: int = 1, src_boxes=None):
        dr, mi = _jit()
        from sionna.rt.path_solvers.paths_buffer import PathsBuffer

        flags = (specular_reflection, diffuse_reflection, refraction, diffraction, edge_diffraction)
        key = (self.fingerprint(), id(mi_scene), tuple(dr.ravel(src_positions).numpy().tolist()), samples_per_src,
               max_depth, flags, seed)
        if src_boxes is not None or max_depth == 0 or key != self._seen:
            # New geometry (or options this cache does not cover): Sionna's own loop.
            self._seen = None if src_boxes is not None else key
            self._key = self._shots = None
            self.paths_counter_per_source = None
            return self.generator(mi_scene, src_positions, tgt_positions, samples_per_src, max_num_paths_per_src,
                                  max_depth, los, specular_reflection, diffuse_reflection, refraction, diffraction,
                                  edge_diffraction, seed, src_boxes)
        if self._key != key:
            self._shots = _shoot(self.generator, mi_scene, src_positions, samples_per_src, max_depth, flags, seed)
            self._key = key
            self.shoots += 1
        shots = self._shots
        assert shots is not None
        num_sources = dr.shape(src_positions)[1]
        paths = PathsBuffer(max_num_paths_per_src * num_sources, max_depth, diffraction)
        counter = dr.zeros(mi.UInt, num_sources)
        if los:
            self.generator._los(mi_scene, src_positions, tgt_positions, paths, counter, None)
        _connect(shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src)
        self.paths_counter_per_source = counter
        self.connects += 1
        return paths


class _Shots:
    """What the shoot phase keeps: per depth, the rays alive there and what the connect
    phase needs of them; over all depths, the sample data the path buffer copies."""

    def __init__(self):
        self.depths: list[dict[str, Any]] = []
        self.samples: Any = None  # SampleDataFields of every ray at every depth (zeros where dead), depth-major
        self.width = 0  # rays
        self.wedges: Any = None  # the diffracting wedge of every ray (first order only)
        self.diffraction_depth: Any = None  # depth of that diffraction, 0 if none
        self.src_indices: Any = None
        self.k_tx: Any = None
        self.counter_size = 0
        self.num_sources = 0


def _shoot(gen, mi_scene, src_positions, samples_per_src: int, max_depth: int, flags, seed: int) -> _Shots:
    """Sionna's bounce loop, one wavefront per depth, without the targets."""
    dr, mi = _jit()
    from sionna.rt.constants import InteractionType
    from sionna.rt.path_solvers.sample_data import SampleData, source_index_per_sample
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator
    from sionna.rt.utils import WedgeGeometry, fibonacci_lattice, hash_fnv1a, spawn_ray_from_sources

    specular_on, diffuse_on, refraction_on, diffraction_on, edge_diffraction_on = flags
    num_sources = dr.shape(src_positions)[1]
    n = samples_per_src * num_sources
    shots = _Shots()
    shots.num_sources = num_sources
    shots.counter_size = max(SBCandidateGenerator.MIN_SPEC_COUNT_SIZE, 0)
    sampler = gen._sampler
    sampler.seed(seed, n)
    shots.width = n
    shots.samples = dr.zeros(SampleData.SampleDataFields, n * max(1, max_depth))
    shots.src_indices = source_index_per_sample(num_sources, samples_per_src)
    ray = spawn_ray_from_sources(fibonacci_lattice, samples_per_src, src_positions)
    shots.k_tx = dr.copy(ray.d)
    specular_chain = dr.full(mi.Bool, True, n)
    hashes = [dr.zeros(mi.UInt64, n) for _ in gen.plane_hash_functions]
    active = dr.full(mi.Mask, True, n)
    enabled = 0
    for on, kind in ((specular_on, InteractionType.SPECULAR), (diffuse_on, InteractionType.DIFFUSE),
                     (refraction_on, InteractionType.REFRACTION), (diffraction_on, InteractionType.DIFFRACTION)):
        if on:
            enabled |= int(kind)
    loc_en_inter = dr.full(mi.UInt, enabled, n)
    shots.wedges = WedgeGeometry.build_with_size(n) if diffraction_on else None
    shots.diffraction_depth = dr.zeros(mi.UInt, n)
    lane = dr.arange(mi.UInt, n)
    for depth in range(1, max_depth + 1):
        si = mi_scene.ray_intersect(ray, coherent=True, ray_flags=mi.RayFlags.Minimal, active=active)
        active &= si.is_valid()
        sample1 = sampler.next_1d()
        sample2 = sampler.next_2d()
        sample2_diffraction = sampler.next_2d()
        s, normal, wedges = gen._sample_radio_material(si, ray.o, ray.d, sample1, sample2, sample2_diffraction,
                                                       loc_en_inter, diffraction_on, edge_diffraction_on, active)
        k_world = s.wo
        int_type = dr.select(active, s.sampled_component, InteractionType.NONE)
        active &= int_type != InteractionType.NONE
        specular = int_type == InteractionType.SPECULAR
        transmission = int_type == InteractionType.REFRACTION
        diffuse = int_type == InteractionType.DIFFUSE
        diffraction = int_type == InteractionType.DIFFRACTION
        loc_en_inter[diffraction] &= ~mi.UInt(InteractionType.DIFFUSE + InteractionType.DIFFRACTION)
        loc_en_inter[diffuse] &= ~mi.UInt(InteractionType.DIFFRACTION)
        specular_chain &= active & (specular | transmission | diffraction)
        # Sample data of this depth (SampleData.insert writes only live rays).
        fields = SampleData.SampleDataFields(
            dr.select(active, int_type, 0), dr.select(active, dr.reinterpret_array(mi.UInt, si.shape), 0),
            dr.select(active, si.prim_index, 0), dr.select(active, si.p, mi.Point3f(0.0)),
            dr.select(active, s.pdf, 0.0))
        dr.scatter(shots.samples, fields, (depth - 1) * n + lane)
        if diffraction_on:
            shots.wedges = dr.select(diffraction, wedges, shots.wedges)
            shots.diffraction_depth = dr.select(diffraction, depth, shots.diffraction_depth)
        for i in range(len(hashes)):
            plane_hash = gen.plane_hash_functions[i](si.n, si.p)
            edge_hash = gen.edge_hash_functions[i](wedges.o, wedges.o + wedges.e_hat * wedges.length)
            inter_hash = dr.select(int_type == InteractionType.SPECULAR, plane_hash, int_type)
            inter_hash = dr.select(int_type == InteractionType.DIFFRACTION, edge_hash, inter_hash)
            hashes[i] = hash_fnv1a(inter_hash, h=hashes[i])
        alive = dr.compress(active)
        record = {"lane": alive, "p": dr.gather(mi.Point3f, si.p, alive), "n": dr.gather(mi.Normal3f, normal, alive),
                  "diffuse": dr.gather(mi.Bool, diffuse, alive),
                  "specular_chain": dr.gather(mi.Bool, specular_chain, alive),
                  "hashes": [dr.gather(mi.UInt64, h, alive) for h in hashes]}
        ray = si.spawn_ray(d=k_world)
        specular_chain |= diffuse
        sampler.schedule_state()
        state = [record, shots.samples, ray, specular_chain, hashes, active, loc_en_inter, shots.wedges,
                 shots.diffraction_depth]
        dr.eval(*[x for x in state if x is not None])
        shots.depths.append(record)
        if dr.width(alive) == 0:
            break
    return shots


class _SampleView:
    """The ``SampleData`` interface over the recorded shoot phase, for chosen rays
    (``lane``: indices of rays) at one depth: what ``PathsBuffer.add_paths`` reads."""

    def __init__(self, shots: _Shots, depth: int, lane):
        dr, mi = _jit()
        from sionna.rt.path_solvers.sample_data import SampleData
        from sionna.rt.utils import WedgeGeometry

        self._shots, self.lane = shots, lane
        self._fields = SampleData.SampleDataFields
        self._src = dr.gather(mi.UInt, shots.src_indices, lane)
        self._wedges = None
        if shots.wedges is not None:
            d = dr.gather(mi.UInt, shots.diffraction_depth, lane)
            seen = (d > 0) & (d <= depth)
            self._wedges = dr.select(seen, dr.gather(WedgeGeometry, shots.wedges, lane),
                                     WedgeGeometry.build_with_size(dr.width(lane)))

    def get(self, depth, active):
        dr, _ = _jit()

        index = (depth - 1) * self._shots.width + self.lane
        data = dr.gather(self._fields, self._shots.samples, index, active)
        return data.interaction_type, data.shape, data.primitive, data.vertex, data.prob

    @property
    def diffracting_wedges(self):
        return self._wedges

    @property
    def src_indices(self):
        return self._src


def _connect(shots: _Shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src: int) -> None:
    """Sionna's inner loop over targets, for every depth: all (target, live ray) pairs
    of a depth at once, target-major; after the visibility test only the pairs that can
    store a path (a visible specular chain, or a diffuse hit with the target on its
    side) go on, in the same order."""
    dr, mi = _jit()
    from sionna.rt.utils import hash_fnv1a

    num_targets = dr.shape(tgt_positions)[1]
    spec_counter_size = max(max_num_paths_per_src, shots.counter_size)
    chain_counters = [dr.zeros(mi.UInt, spec_counter_size * shots.num_sources) for _ in range(2)]
    dr.make_opaque(counter, *chain_counters)
    for depth, rec in enumerate(shots.depths, start=1):
        live = dr.width(rec["lane"])
        if live == 0:
            break
        t = dr.repeat(dr.arange(mi.UInt, num_targets), live)
        j = dr.tile(dr.arange(mi.UInt, live), num_targets)
        normal = dr.gather(mi.Normal3f, rec["n"], j)
        si = dr.zeros(mi.SurfaceInteraction3f, live * num_targets)
        si.p, si.n = dr.gather(mi.Point3f, rec["p"], j), normal
        los_ray = si.spawn_ray_to(dr.gather(mi.Point3f, tgt_positions, t))
        visible = ~mi_scene.ray_test(los_ray)
        valid = visible & dr.gather(mi.Bool, rec["diffuse"], j) & (dr.dot(normal, los_ray.d) > 0.0)
        new_specular = dr.gather(mi.Bool, rec["specular_chain"], j) & visible
        direction = mi.Vector3f(los_ray.d)
        dr.eval(valid, new_specular, direction)  # one visibility kernel
        pick = dr.compress(valid | new_specular)  # increasing: the order is kept
        k = dr.width(pick)
        if k == 0:
            continue
        t, j = dr.gather(mi.UInt, t, pick), dr.gather(mi.UInt, j, pick)
        k_rx = -dr.gather(mi.Vector3f, direction, pick)
        valid, new_specular = dr.gather(mi.Bool, valid, pick), dr.gather(mi.Bool, new_specular, pick)
        dr.eval(t, j, k_rx, valid, new_specular)
        view = _SampleView(shots, depth, dr.gather(mi.UInt, rec["lane"], j))
        src = view.src_indices
        for i, h in enumerate(rec["hashes"]):
            path_target_hash = hash_fnv1a(t, h=dr.gather(mi.UInt64, h, j))
            index = mi.UInt(path_target_hash % spec_counter_size) + spec_counter_size * src
            seen = dr.scatter_inc(chain_counters[i], index, new_specular)
            dr.eval(seen)  # the output of an atomic increment feeds later kernels: evaluate it now
            new_specular &= seen == 0
        store = valid | new_specular
        per_source = dr.scatter_inc(counter, src, store)
        dr.eval(per_source)
        store &= per_source < max_num_paths_per_src
        path_ind = dr.scatter_inc(paths.paths_counter, mi.UInt(0), store)
        dr.eval(path_ind)
        k_tx = dr.gather(mi.Vector3f, shots.k_tx, view.lane)
        paths.add_paths(mi.UInt(depth), path_ind, view, valid, t, k_tx, k_rx, store)
        paths.schedule()
        dr.eval(counter, *chain_counters)
