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
* **connect** (every solve): per depth, the visibility of each target from the live
  rays' hit points (Sionna's test), the specular-chain deduplication and the storing of
  paths, as in Sionna's inner loop but over the live rays only (Sionna's loop runs every
  ray of a packet until the last one dies). A target behind the plane of a chain's last
  reflection is not tested: no specular path ends there (:func:`_behind_reflections`);
  Sionna tests it and the image method drops the candidate.

Deduplication is exact here. Sionna marks a specular chain as seen in a table of
max(``max_num_paths_per_src``, 1e6) counters indexed by hash modulo its size, and a
chain whose slot another chain took is dropped silently. With 1e6 samples and 10
receivers in one solve that loses about a fifth of the paths (Central Park: 123 instead
of 161 paths, up to 2.5 dB of path gain; a table 8x larger finds 160). Here chains are
grouped by hash, and a (chain, target) pair is stored from the first ray of its group
that sees the target, in ray order, with Sionna's rule for its two hashes kept.

The paths are then those of Sionna's loop without collisions: the same rays, hits and
tests; the order in which candidates land in the buffer differs (depth-major here), so
sums over paths differ in the last float bits, and another ray of a chain may be the
one stored (the image method refines each chain to the same path).
``tests/test_shoot_cache.py`` compares with Sionna's loop.

The cache is keyed on a fingerprint of the geometry (objects' positions, orientations,
scales and materials, the frequency, the sources and the solver settings). A
fingerprint seen for the first time is traced by Sionna's own generator; the shoot phase
is recorded when the same fingerprint comes back, so a scene whose objects move every
step costs nothing extra.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Hashable, Sequence
from typing import Any

import numpy as np


def _array(cls, values: np.ndarray):
    """A Dr.Jit array of ``values``, made from 64-byte aligned memory: Dr.Jit takes numpy's
    memory as it is and compiles a kernel anew for each alignment it meets."""
    values = np.ascontiguousarray(values)
    buf = np.empty(values.nbytes + 64, dtype=np.uint8)
    start = -buf.ctypes.data % 64
    aligned = buf[start:start + values.nbytes].view(values.dtype)
    aligned[...] = values.ravel()
    return cls(aligned)


def _jit() -> tuple[Any, Any]:
    """Dr.Jit and Mitsuba, untyped: Dr.Jit's stubs do not know Mitsuba's array types."""
    import drjit
    import mitsuba

    return drjit, mitsuba


class ShootCache:
    """A drop-in for the solver's candidate generator (see the module docstring); every
    Sionna internal it uses goes through :mod:`caviar_plugins.radio.sionna_internals`.

    ``fingerprint()`` returns a hashable description of everything but the targets that
    the bounces depend on; :meth:`RadioScene` supplies one. ``movers()`` (optional) returns
    the scene objects that move from solve to solve (UAV bodies, vehicles) and that the
    fingerprint leaves out: the bounces are recorded with them moved out of the way, and each
    solve's visibility tests (and the image method after it) run in the scene with them where
    they are, so the paths they block are dropped; the paths by way of them come from rays
    aimed at each (``rays_for(obj)`` of them, :data:`RAYS_PER_MOVING_OBJECT` without it; None:
    Sionna's own rays from the source that now meet it first, :func:`_first_rays_met`; 0: none,
    for an object parked out of the scene) and from the recorded rays that now meet one after
    a bounce (see :func:`_by_way_of_movers`). ``boxes_of(obj)`` (optional) gives the bounds
    (m, 2, 3) of an object's separate bodies (a pool of boxes in one mesh), each then aimed at
    and prefiltered on its own; without it, the object's bounding box.
    """

    cull_behind = True
    """Whether targets behind a chain's last reflecting plane go untested
    (:func:`_behind_reflections`); False tests them as Sionna does, for comparison."""

    def __init__(self, generator: Any, fingerprint: Callable[[], Hashable],
                 movers: Callable[[], Sequence[Any]] | None = None, scene: Any = None,
                 rays_for: Callable[[Any], int | None] | None = None,
                 boxes_of: Callable[[Any], np.ndarray] | None = None):
        self.generator = generator
        self.boxes_of = boxes_of
        self.fingerprint = fingerprint
        self.movers = movers
        self.scene = scene
        self.rays_per_moving_object = RAYS_PER_MOVING_OBJECT
        self.rays_for = rays_for
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
        self.visibility_tests = 0
        """Visibility tests (a ray from a hit point to a target) made by the solves served."""

    @property
    def has_seen_geometry(self) -> bool:
        """Whether the last solve's geometry was seen, so that the next solve with it is
        served from the cache (a resumed run sees it once more before going on)."""
        return self._seen is not None

    def __call__(self, mi_scene, src_positions, tgt_positions, samples_per_src: int, max_num_paths_per_src: int,
                 max_depth: int, los: bool, specular_reflection: bool, diffuse_reflection: bool, refraction: bool,
                 diffraction: bool, edge_diffraction: bool, seed: int = 1, src_boxes=None):
        dr, mi = _jit()
        from caviar_plugins.radio import sionna_internals as internals

        flags = (specular_reflection, diffuse_reflection, refraction, diffraction, edge_diffraction)
        key = (self.fingerprint(), id(mi_scene), tuple(dr.ravel(src_positions).numpy().tolist()), samples_per_src,
               max_depth, flags, seed)
        # More than one source (several transmitters, or synthetic_array = false): Sionna
        # deduplicates chains per source, this cache does not yet, so Sionna's loop runs.
        if src_boxes is not None or max_depth == 0 or dr.shape(src_positions)[1] != 1 or key != self._seen:
            # New geometry (or options this cache does not cover): Sionna's own loop.
            self._seen = None if src_boxes is not None else key
            self._key = self._shots = None
            self.paths_counter_per_source = None
            return self.generator(mi_scene, src_positions, tgt_positions, samples_per_src, max_num_paths_per_src,
                                  max_depth, los, specular_reflection, diffuse_reflection, refraction, diffraction,
                                  edge_diffraction, seed, src_boxes)
        moving = list(self.movers()) if self.movers is not None else []
        if self._key != key or self._shots is None or (moving and not self._shots.keeps_state):
            with internals.objects_out_of_the_way(self.scene, moving):
                self._shots = _shoot(self.generator, mi_scene, src_positions, samples_per_src, max_depth, flags,
                                     seed, keep_state=bool(moving))
            self._key = key
            self.shoots += 1
        shots = self._shots
        assert shots is not None
        num_sources = dr.shape(src_positions)[1]
        paths = internals.new_paths_buffer(max_num_paths_per_src * num_sources, max_depth, diffraction)
        counter = dr.zeros(mi.UInt, num_sources)
        if los:
            internals.add_line_of_sight(self.generator, mi_scene, src_positions, tgt_positions, paths, counter)
        if not moving:
            self.visibility_tests += _connect(shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src,
                                              self.cull_behind)
        else:
            per_object = [self.boxes_of(o) if self.boxes_of is not None else bounding_box(o) for o in moving]
            boxes = np.concatenate([np.zeros((0, 2, 3))] + [np.asarray(b, dtype=float).reshape(-1, 2, 3)
                                                            for b in per_object])
            source = np.array(dr.ravel(src_positions).numpy(), dtype=float)[:3]
            asked_per_object = [self.rays_for(o) if self.rays_for is not None else self.rays_per_moving_object
                                for o in moving]
            asked = [n for n, b in zip(asked_per_object, per_object, strict=True) for _ in range(len(b))]
            spheres = [(box.mean(axis=0), np.linalg.norm(box[1] - box[0]) / 2) for box in boxes]
            aimed = np.concatenate([np.zeros((0, 3))] + [
                aim_at(source, centre, radius, n) for (centre, radius), n in zip(spheres, asked, strict=True)
                if n is not None and n > 0])
            present = boxes[[n is None or n > 0 for n in asked]]
            near = _boxes_scene(present) if len(present) else None
            # Objects given no count (None): Sionna's own first rays (the recorded ones from the
            # source) that now meet one of them first (the boxes of all present objects
            # prefilter them; the shape table keeps those on these objects).
            own = [obj for obj, n in zip(moving, asked_per_object, strict=True) if n is None]
            first = _first_rays_met(mi_scene, shots, source, _shape_table(self.scene, own), near) if own \
                else np.zeros((0, 3))
            table = _shape_table(self.scene, moving)
            picked = _met_by_movers(mi_scene, shots, max_depth, table, near)
            # Sionna's image method re-checks the segments of specular chains, not of diffuse
            # paths: a diffuse path whose earlier segments now meet a moving object is dropped
            # here. And a ray goes on from the first moving object it meets only: a recorded
            # ray blocked before a later meeting is not continued from there.
            blocked = _blocked_from(mi_scene, shots, source, table, near, picked)
            if blocked is not None:
                picked = [(d, pick[blocked[shots.depths[d - 1]["lanes"][pick]] == d]) for d, pick in picked]
                picked = [(d, pick) for d, pick in picked if len(pick)]
            self.visibility_tests += _connect(shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src,
                                              self.cull_behind, blocked)
            # Paths by way of the moving objects (see _by_way_of_movers).
            more = _by_way_of_movers(self.generator, mi_scene, shots, src_positions, max_depth, flags, seed,
                                     table, aimed, near, first, picked)
            if more is not None:
                self.visibility_tests += _connect(more, mi_scene, tgt_positions, paths, counter,
                                                  max_num_paths_per_src, self.cull_behind)
        self.paths_counter_per_source = counter
        self.connects += 1
        return paths


def bounding_box(obj) -> np.ndarray:
    """A scene object's bounding box as bounds (1, 2, 3)."""
    box = obj.mi_mesh.bbox()
    return np.array([[np.array(box.min), np.array(box.max)]], dtype=float)


RAYS_PER_MOVING_OBJECT = 4096
"""Rays aimed at each moving body's bounding sphere per solve (about 5 cm apart on a
2 m UAV body, against about 1.3 m for 3e5 rays over the whole sphere at 200 m)."""
PAD_RAYS = 1024
"""The rays by way of moving objects come in multiples of this (see :func:`_by_way_of_movers`)."""


def _shape_table(scene, objects) -> Any:
    """A Dr.Jit Bool array indexed by Mitsuba shape id (a hit's ``si.shape`` as UInt32):
    true for the shapes of ``objects``, false for every other shape and for "no shape" (0).
    One gather per hit then tells whether it is on a moving object, whatever their number."""
    dr, mi = _jit()
    ids = [int(o.object_id) for o in objects]
    size = max([int(o.object_id) for o in scene.objects.values()] + ids) + 2  # the last entry: any other id
    table = np.zeros(size, dtype=bool)
    table[ids] = True
    return _array(mi.Bool, table)


def _on_shapes(table, si) -> Any:
    """Whether each hit of ``si`` (a surface or preliminary intersection) lies on a shape that
    ``table`` (:func:`_shape_table`) marks."""
    dr, mi = _jit()
    ids = dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), dr.width(table) - 1)
    return si.is_valid() & dr.gather(mi.Bool, table, ids, si.is_valid())


def aim_at(source: np.ndarray, center: np.ndarray, radius: float, count: int) -> np.ndarray:
    """``count`` unit directions from ``source`` spread evenly (a Fibonacci spiral) over the
    cone that holds the sphere of ``radius`` about ``center`` (the whole sphere of
    directions when the source is inside it)."""
    axis = np.asarray(center, dtype=float) - np.asarray(source, dtype=float)
    dist = float(np.linalg.norm(axis))
    cos_half = np.sqrt(1 - (radius / dist) ** 2) if dist > radius else -1.0
    i = np.arange(count) + 0.5
    z = 1 - (1 - cos_half) * i / count
    r = np.sqrt(np.maximum(0.0, 1 - z**2))
    phi = i * np.pi * (3 - np.sqrt(5))
    local = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    w = axis / dist if dist > 0 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    return local @ np.stack([u, v, w])


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
        self.keeps_state = False  # whether each depth keeps where its rays go next (moving objects)


def _shoot(gen, mi_scene, src_positions, samples_per_src: int, max_depth: int, flags, seed: int,
           keep_state: bool = False) -> _Shots:
    """Sionna's bounce loop, one wavefront per depth, without the targets.

    ``keep_state``: each depth's record also keeps what a ray needs to go on from there
    (:func:`_by_way_of_movers`)."""
    shots, state = _first_rays(gen, src_positions, samples_per_src, max_depth, flags, seed)
    shots.keeps_state = keep_state
    _bounce(gen, mi_scene, shots, state, max_depth, flags, keep_state=keep_state)
    return shots


def _first_rays(gen, src_positions, samples_per_src: int, max_depth: int, flags, seed: int) -> tuple[_Shots, dict]:
    """The shots of :func:`_shoot` before any bounce, and the rays' state as Sionna's loop
    starts it (its Fibonacci lattice from each source, its sampler seeded)."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    InteractionType, WedgeGeometry, fibonacci_lattice, _, spawn_ray_from_sources = internals.ray_utilities()
    specular_on, diffuse_on, refraction_on, diffraction_on, _ = flags
    num_sources = dr.shape(src_positions)[1]
    n = samples_per_src * num_sources
    shots = _Shots()
    internals.sampler(gen).seed(seed, n)
    shots.width = n
    shots.samples = dr.zeros(internals.sample_data_fields(), n * max(1, max_depth))
    shots.src_indices = internals.source_index_per_sample(num_sources, samples_per_src)
    ray = spawn_ray_from_sources(fibonacci_lattice, samples_per_src, src_positions)
    shots.k_tx = dr.copy(ray.d)
    enabled = 0
    for on, kind in ((specular_on, InteractionType.SPECULAR), (diffuse_on, InteractionType.DIFFUSE),
                     (refraction_on, InteractionType.REFRACTION), (diffraction_on, InteractionType.DIFFRACTION)):
        if on:
            enabled |= int(kind)
    shots.wedges = WedgeGeometry.build_with_size(n) if diffraction_on else None
    shots.diffraction_depth = dr.zeros(mi.UInt, n)
    state = {"ray": ray, "specular_chain": dr.full(mi.Bool, True, n),
             "hashes": [dr.zeros(mi.UInt64, n) for _ in internals.hashers(gen)[0]],
             "active": dr.full(mi.Mask, True, n), "loc_en_inter": dr.full(mi.UInt, enabled, n)}
    return shots, state


def _interact(gen, mi_scene, sampler, ray, active, loc_en_inter, specular_chain, hashes, flags, waiting=None):
    """One depth of Sionna's bounce loop without the targets, for the rays of ``ray``: the
    hit, the sampled interaction (Sionna's material and wedge sampling, its random numbers),
    the locally enabled interactions, the specular-chain flag and hashes updated, and the
    sample data of this depth. Rays in ``waiting`` (optional) keep their flag and hashes.
    Returns a dict; ``active`` is the rays that interacted."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    InteractionType, _, _, hash_fnv1a, _ = internals.ray_utilities()
    plane_hashers, edge_hashers = internals.hashers(gen)
    _, _, _, diffraction_on, edge_diffraction_on = flags
    si = mi_scene.ray_intersect(ray, coherent=True, ray_flags=mi.RayFlags.Minimal, active=active)
    active = active & si.is_valid()
    sample1 = sampler.next_1d()
    sample2 = sampler.next_2d()
    sample2_diffraction = sampler.next_2d()
    s, normal, wedges = internals.sample_radio_material(gen, si, ray.o, ray.d, sample1, sample2, sample2_diffraction,
                                                        loc_en_inter, diffraction_on, edge_diffraction_on, active)
    int_type = dr.select(active, s.sampled_component, InteractionType.NONE)
    active &= int_type != InteractionType.NONE
    specular = int_type == InteractionType.SPECULAR
    transmission = int_type == InteractionType.REFRACTION
    diffuse = int_type == InteractionType.DIFFUSE
    diffraction = int_type == InteractionType.DIFFRACTION
    no_more = ~mi.UInt(InteractionType.DIFFUSE + InteractionType.DIFFRACTION)
    loc_en_inter = dr.select(diffraction, loc_en_inter & no_more, loc_en_inter)
    loc_en_inter = dr.select(diffuse, loc_en_inter & ~mi.UInt(InteractionType.DIFFRACTION), loc_en_inter)
    chain = specular_chain & active & (specular | transmission | diffraction)
    new_hashes = []
    for i, h in enumerate(hashes):
        plane_hash = plane_hashers[i](si.n, si.p)
        edge_hash = edge_hashers[i](wedges.o, wedges.o + wedges.e_hat * wedges.length)
        inter_hash = dr.select(int_type == InteractionType.SPECULAR, plane_hash, int_type)
        inter_hash = dr.select(int_type == InteractionType.DIFFRACTION, edge_hash, inter_hash)
        new_hashes.append(hash_fnv1a(inter_hash, h=h))
    if waiting is not None:
        chain = dr.select(waiting, specular_chain, chain)
        new_hashes = [dr.select(waiting, h, new) for h, new in zip(hashes, new_hashes, strict=True)]
    # Sample data of this depth (SampleData.insert writes only live rays).
    fields = internals.sample_data_fields()(
        dr.select(active, int_type, 0), dr.select(active, dr.reinterpret_array(mi.UInt, si.shape), 0),
        dr.select(active, si.prim_index, 0), dr.select(active, si.p, mi.Point3f(0.0)), dr.select(active, s.pdf, 0.0))
    return {"si": si, "normal": normal, "wedges": wedges, "k_world": s.wo, "active": active,
            "loc_en_inter": loc_en_inter, "specular_chain": chain, "hashes": new_hashes, "diffuse": diffuse,
            "diffraction": diffraction, "fields": fields}


def _record(lane, index, p, n, diffuse, specular_chain, hashes) -> dict[str, Any]:
    """A depth's record of the rays ``lane`` (what :func:`_connect` reads), gathered at
    ``index`` from arrays of hit points, normals, diffuse flags, chain flags and hashes."""
    dr, mi = _jit()
    return {"lane": lane, "p": dr.gather(mi.Point3f, p, index), "n": dr.gather(mi.Normal3f, n, index),
            "diffuse": dr.gather(mi.Bool, diffuse, index), "specular_chain": dr.gather(mi.Bool, specular_chain, index),
            "hashes": [dr.gather(mi.UInt64, h, index) for h in hashes]}


def _bounce(gen, mi_scene, shots: _Shots, state: dict, max_depth: int, flags, keep_state: bool) -> None:
    """The recorded bounces of the static scene (:func:`_shoot`): Sionna's inner loop without
    the targets, one wavefront per depth, appending one record per depth to ``shots.depths``
    (the rays still alive there)."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    sampler = internals.sampler(gen)
    diffraction_on = flags[3]
    n = shots.width
    ray, specular_chain, hashes = state["ray"], state["specular_chain"], state["hashes"]
    active, loc_en_inter = state["active"], state["loc_en_inter"]
    lane = dr.arange(mi.UInt, n)
    for depth in range(1, max_depth + 1):
        x = _interact(gen, mi_scene, sampler, ray, active, loc_en_inter, specular_chain, hashes, flags)
        si, normal, active, loc_en_inter = x["si"], x["normal"], x["active"], x["loc_en_inter"]
        specular_chain, hashes, diffuse = x["specular_chain"], x["hashes"], x["diffuse"]
        k_world = x["k_world"]
        dr.scatter(shots.samples, x["fields"], dr.opaque(mi.UInt, (depth - 1) * n) + lane)
        if diffraction_on:
            shots.wedges = dr.select(x["diffraction"], x["wedges"], shots.wedges)
            shots.diffraction_depth = dr.select(x["diffraction"], depth, shots.diffraction_depth)
        hit_p, chain_here = si.p, specular_chain
        ray = si.spawn_ray(d=k_world)
        specular_chain = specular_chain | diffuse
        sampler.schedule_state()
        # Everything of this depth in one kernel: a gather from an array not yet evaluated
        # would trace and run the intersection and the material sampling again for it.
        depth_state = [hit_p, normal, diffuse, chain_here, hashes, shots.samples, ray, specular_chain, active,
                       loc_en_inter, shots.wedges, shots.diffraction_depth]
        dr.eval(*[x for x in depth_state if x is not None])
        alive = dr.compress(active)
        record = _record(alive, alive, hit_p, normal, diffuse, chain_here, hashes)
        if keep_state:  # where each live ray goes next, and its state: for rays that now meet a moving object
            record.update({"o": dr.gather(mi.Point3f, ray.o, alive), "d": dr.gather(mi.Vector3f, ray.d, alive),
                           "chain_next": dr.gather(mi.Bool, specular_chain, alive),
                           "loc": dr.gather(mi.UInt, loc_en_inter, alive)})
        dr.eval(record)
        _group_chains(record)
        shots.depths.append(record)
        if dr.width(alive) == 0:
            break


def _bounce_in_one_loop(gen, mi_scene, shots: _Shots, state: dict, max_depth: int, flags, touch_shapes,
                        start) -> None:
    """:func:`_bounce` (without ``keep_state``) as one Dr.Jit symbolic loop: its body is
    traced once per solve instead of once per depth (the tracing of Sionna's material and
    wedge sampling, not the rays, is what a few thousand rays cost), and each depth's
    record is written to flat buffers (depth-major) that are compressed afterwards. Each
    depth is :func:`_interact`, as in :func:`_bounce`; besides, a ray waits until its
    ``start`` depth, and with ``touch_shapes`` (:func:`_shape_table`) it is recorded only from
    its first hit on one of those shapes on."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    sampler = internals.sampler(gen)
    n = shots.width
    width = dr.opaque(mi.UInt, n)
    lane = dr.arange(mi.UInt, n)
    size = n * max_depth
    out = {"recorded": dr.zeros(mi.Bool, size), "p": dr.zeros(mi.Point3f, size), "n": dr.zeros(mi.Normal3f, size),
           "diffuse": dr.zeros(mi.Bool, size), "specular_chain": dr.zeros(mi.Bool, size),
           "hashes": [dr.zeros(mi.UInt64, size) for _ in state["hashes"]]}
    with_wedges = shots.wedges is not None
    wedges_state = shots.wedges if with_wedges else mi.UInt(0)
    diffraction_depth = shots.diffraction_depth if with_wedges else mi.UInt(0)

    def cond(depth, *_):
        return depth <= max_depth

    def body(depth, ray, specular_chain, hashes, active, loc_en_inter, touched, wedges_kept, ddepth, sampler_):
        waiting = start > depth
        before = active
        x = _interact(gen, mi_scene, sampler_, ray, active & ~waiting, loc_en_inter, specular_chain, hashes, flags,
                      waiting)
        si, normal, active, loc_en_inter = x["si"], x["normal"], x["active"], x["loc_en_inter"]
        specular_chain, hashes, diffuse = x["specular_chain"], x["hashes"], x["diffuse"]
        k_world = x["k_world"]
        at = (depth - 1) * width + lane
        dr.scatter(shots.samples, x["fields"], at, ~waiting)
        if with_wedges:
            wedges_kept = dr.select(x["diffraction"], x["wedges"], wedges_kept)
            ddepth = dr.select(x["diffraction"], depth, ddepth)
        if touch_shapes is not None:
            touched |= active & _on_shapes(touch_shapes, si)
        recorded = active & touched
        dr.scatter(out["recorded"], recorded, at)
        for key, value in (("p", si.p), ("n", normal), ("diffuse", diffuse), ("specular_chain", specular_chain)):
            dr.scatter(out[key], value, at, recorded)
        for i, h in enumerate(hashes):
            dr.scatter(out["hashes"][i], h, at, recorded)
        ray = dr.select(waiting, ray, si.spawn_ray(d=k_world))
        specular_chain = specular_chain | diffuse
        active = dr.select(waiting, before, active)
        return (depth + 1, ray, specular_chain, hashes, active, loc_en_inter, touched, wedges_kept, ddepth,
                sampler_)

    loop_state = (dr.full(mi.UInt, 1, n), state["ray"], state["specular_chain"], list(state["hashes"]),
                  state["active"], state["loc_en_inter"], state["touched"], wedges_state, diffraction_depth, sampler)
    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        result = dr.while_loop(loop_state, cond, body, label="caviar_moving_objects")
    if with_wedges:
        shots.wedges, shots.diffraction_depth = result[7], result[8]
    dr.eval(out, shots.samples, shots.wedges, shots.diffraction_depth)
    recorded = np.asarray(out["recorded"], dtype=bool).reshape(max_depth, n)
    for depth in range(1, max_depth + 1):
        rays = np.flatnonzero(recorded[depth - 1])
        if not recorded[depth - 1:].any():
            break
        if len(rays) == 0:  # (nothing recorded at this depth, more later: an empty record keeps the depths' order)
            shots.depths.append({"lane": mi.UInt()})
            continue
        alive = _array(mi.UInt, rays.astype(np.uint32))
        record = _record(alive, dr.opaque(mi.UInt, (depth - 1) * n) + alive, out["p"], out["n"], out["diffuse"],
                         out["specular_chain"], out["hashes"])
        dr.eval(record)
        _group_chains(record)
        shots.depths.append(record)


BOX_MARGIN_M = 0.01
"""How much the boxes of :func:`_boxes_scene` stand out of the objects' bounding boxes."""

# Corners of the unit cube (corner i: x from bit 0, y from bit 1, z from bit 2) and its 12
# triangles, outward.
_CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
_CUBE_FACES = np.array([(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4), (2, 6, 7), (2, 7, 3),
                        (0, 4, 6), (0, 6, 2), (1, 3, 7), (1, 7, 5)], dtype=np.uint32)


def _boxes_scene(boxes: np.ndarray) -> Any:
    """A Mitsuba scene of nothing but ``boxes`` ((m, 2, 3): each object's bounding box, grown
    by :data:`BOX_MARGIN_M`), one mesh: a ray that meets none of them meets none of the
    objects, and testing a few ten thousand rays against it costs well under a millisecond
    (a ray test in the whole scene, tens of milliseconds)."""
    dr, mi = _jit()
    lo = boxes[:, 0] - BOX_MARGIN_M
    hi = boxes[:, 1] + BOX_MARGIN_M
    vertices = lo[:, None, :] + _CORNERS[None] * (hi - lo)[:, None, :]  # (m, 8, 3)
    faces = _CUBE_FACES[None] + (8 * np.arange(len(boxes), dtype=np.uint32))[:, None, None]
    mesh = mi.Mesh("moving-object-boxes", vertex_count=8 * len(boxes), face_count=12 * len(boxes),
                   has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mi.load_dict({"type": "scene", "boxes": mesh})


def _met_by_movers(mi_scene, shots: _Shots, max_depth: int, movers, near) -> list[tuple[int, np.ndarray]]:
    """The recorded rays whose next segment now meets a moving object first, as (depth, indices
    into that depth's record): those that meet one of the objects' boxes (``near``,
    :func:`_boxes_scene`; None: all parked, none) are cast again in the whole scene, and kept
    where the first shape hit is one of ``movers`` (:func:`_shape_table`)."""
    dr, mi = _jit()
    picked = []
    for d, rec in enumerate(shots.depths[: max_depth - 1], start=1):
        if near is None or dr.width(rec["lane"]) == 0 or "o" not in rec:
            continue
        ahead = dr.compress(near.ray_test(mi.Ray3f(rec["o"], rec["d"])))
        if dr.width(ahead) == 0:
            continue
        # (Which shape is hit first is all that is needed: the preliminary intersection,
        # without the surface interaction's call into every shape of the scene, about 8 ms.)
        hit = mi_scene.ray_intersect_preliminary(mi.Ray3f(dr.gather(mi.Point3f, rec["o"], ahead),
                                                          dr.gather(mi.Vector3f, rec["d"], ahead)),
                                                 coherent=False)
        on = np.asarray(_on_shapes(movers, hit), dtype=bool)
        pick = np.asarray(ahead, dtype=np.int64)[on]
        if len(pick):
            picked.append((d, pick))
    return picked


def _source_lanes_met(mi_scene, shots: _Shots, source: np.ndarray, table, near,
                      lanes: np.ndarray | None = None) -> np.ndarray:
    """The lanes (of ``lanes``; None: all) whose recorded ray from the source (Sionna's
    Fibonacci lattice, ``shots.k_tx``) now hits a shape that ``table`` marks first: those that
    meet one of the boxes of ``near`` (:func:`_boxes_scene`, boxes around those shapes and
    maybe others) are cast again in the whole scene."""
    dr, mi = _jit()
    origin = mi.Point3f(*(float(x) for x in source))
    if lanes is None:
        lanes = np.arange(shots.width, dtype=np.int64)
        k = shots.k_tx
    else:
        k = dr.gather(mi.Vector3f, shots.k_tx, _array(mi.UInt, lanes.astype(np.uint32)))
    ahead = np.flatnonzero(np.asarray(near.ray_test(mi.Ray3f(origin, k)), dtype=bool))
    if len(ahead) == 0:
        return np.zeros(0, dtype=np.int64)
    d = dr.gather(mi.Vector3f, k, _array(mi.UInt, ahead.astype(np.uint32)))
    on = np.asarray(_on_shapes(table, mi_scene.ray_intersect_preliminary(mi.Ray3f(origin, d), coherent=False)),
                    dtype=bool)
    return lanes[ahead[on]]


def _first_rays_met(mi_scene, shots: _Shots, source: np.ndarray, table, near) -> np.ndarray:
    """The directions (m, 3) of the recorded rays from the source whose first hit is now on a
    shape that ``table`` marks (:func:`_source_lanes_met`)."""
    dr, mi = _jit()
    lanes = _source_lanes_met(mi_scene, shots, source, table, near)
    d = dr.gather(mi.Vector3f, shots.k_tx, _array(mi.UInt, lanes.astype(np.uint32)))
    return np.array(d, dtype=float).reshape(3, -1).T


NOT_BLOCKED = np.iinfo(np.int32).max


def _blocked_from(mi_scene, shots: _Shots, source: np.ndarray, movers, near,
                  picked: list[tuple[int, np.ndarray]]) -> np.ndarray | None:
    """Per lane of the recorded bounces, the first segment that now meets a moving object
    first (segment 0: source to first hit; segment d: the hit at depth d to the next), or
    :data:`NOT_BLOCKED`, for the lanes that end a diffuse path or meet a moving object
    after a bounce (``picked``, from :func:`_met_by_movers`); None when there are none or no
    object is near. Segments d >= 1 come from ``picked``; segment 0 from
    :func:`_source_lanes_met`."""
    dr, _ = _jit()
    if near is None:
        return None
    asked = [rec["lanes"][rec["diffuse_rays"]] for rec in shots.depths
             if dr.width(rec["lane"]) and len(rec["diffuse_rays"])]
    asked += [shots.depths[d - 1]["lanes"][pick] for d, pick in picked]
    if not asked:
        return None
    blocked = np.full(shots.width, NOT_BLOCKED, dtype=np.int64)
    for d, pick in reversed(picked):  # the earliest segment wins
        blocked[shots.depths[d - 1]["lanes"][pick]] = d
    blocked[_source_lanes_met(mi_scene, shots, source, movers, near, np.unique(np.concatenate(asked)))] = 0
    return blocked


def _by_way_of_movers(gen, mi_scene, shots: _Shots, src_positions, max_depth: int, flags, seed: int, movers,
                      aimed: np.ndarray, near=None, first: np.ndarray | None = None,
                      picked: list[tuple[int, np.ndarray]] | None = None) -> _Shots | None:
    """The rays that meet a moving object, bounced in the scene as it is now and connected
    from their first hit on one (one bounce loop for all, each ray setting off at its own
    depth):

    * ``aimed`` rays from the source at the objects (depth 1), for the paths that meet one
      first, with the diffuse branch off (their density is not Sionna's);
    * ``first``: Sionna's own rays from the source (directions) that meet one first
      (:func:`_first_rays_met`), with every interaction Sionna's loop enables;
    * the rays of the recorded bounces that now meet one after a bounce on the static scene
      (Sionna's loop, run now, would send them onto it): each goes on from the depth at which
      it meets it, with the interactions it had before (``picked``: :func:`_met_by_movers`'s
      answer, when the caller has it)."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    InteractionType, WedgeGeometry, _, _, _ = internals.ray_utilities()
    sample_fields = internals.sample_data_fields()
    specular_on, diffuse_on, refraction_on, diffraction_on, _ = flags
    if picked is None:
        picked = _met_by_movers(mi_scene, shots, max_depth, movers, near)
    first = np.zeros((0, 3)) if first is None else first
    a = len(aimed) + len(first)
    used = a + sum(len(pick) for _, pick in picked)
    if used == 0:  # every moving object parked, none met: no paths by way of them
        return None
    # Padded to a multiple of PAD_RAYS with rays that never set off: Dr.Jit compiles the loop
    # anew for a new width, and the number of rays met varies from solve to solve.
    k = -(-used // PAD_RAYS) * PAD_RAYS
    out = _Shots()
    out.width = k
    out.samples = dr.zeros(sample_fields, k * max_depth)
    enabled = sum(int(kind) for on, kind in ((specular_on, InteractionType.SPECULAR),
                                             (refraction_on, InteractionType.REFRACTION),
                                             (diffraction_on, InteractionType.DIFFRACTION)) if on)
    all_enabled = enabled | (int(InteractionType.DIFFUSE) if diffuse_on else 0)
    origin = np.repeat(np.array(dr.ravel(src_positions).numpy(), dtype=np.float32)[None, :3], a, axis=0)
    start_dirs = np.concatenate([aimed, first]).astype(np.float32)
    o, d_, k_tx = [origin], [start_dirs], [start_dirs]
    chain, h0, h1 = [np.ones(a, bool)], [np.zeros(a, np.uint64)], [np.zeros(a, np.uint64)]
    loc = [np.r_[np.full(len(aimed), enabled, np.uint32), np.full(len(first), all_enabled, np.uint32)]]
    start, src = [np.ones(a, np.uint32)], [np.zeros(a, np.uint32)]
    wedges = WedgeGeometry.build_with_size(k) if shots.wedges is not None else None
    diffraction_depth = dr.zeros(mi.UInt, k)
    offset = a
    for d, pick in picked:
        rec = shots.depths[d - 1]
        idx = _array(mi.UInt, pick.astype(np.uint32))
        lanes = dr.gather(mi.UInt, rec["lane"], idx)
        slots = dr.opaque(mi.UInt, offset) + dr.arange(mi.UInt, len(pick))
        for dd in range(1, d + 1):  # the interactions before, as recorded
            dr.scatter(out.samples, dr.gather(sample_fields, shots.samples,
                                              dr.opaque(mi.UInt, (dd - 1) * shots.width) + lanes),
                       dr.opaque(mi.UInt, (dd - 1) * k) + slots)
        if wedges is not None:
            ddep = dr.gather(mi.UInt, shots.diffraction_depth, lanes)
            earlier = (ddep > 0) & (ddep <= d)
            dr.scatter(wedges, dr.gather(WedgeGeometry, shots.wedges, lanes), slots, earlier)
            dr.scatter(diffraction_depth, ddep, slots, earlier)
        o.append(np.array(dr.gather(mi.Point3f, rec["o"], idx), dtype=np.float32).reshape(3, -1).T)
        d_.append(np.array(dr.gather(mi.Vector3f, rec["d"], idx), dtype=np.float32).reshape(3, -1).T)
        k_tx.append(np.array(dr.gather(mi.Vector3f, shots.k_tx, lanes), dtype=np.float32).reshape(3, -1).T)
        chain.append(np.asarray(dr.gather(mi.Bool, rec["chain_next"], idx), dtype=bool))
        loc.append(np.asarray(dr.gather(mi.UInt, rec["loc"], idx), dtype=np.uint32))
        h0.append(rec["h0"][pick])
        h1.append(rec["h1"][pick])
        start.append(np.full(len(pick), d + 1, np.uint32))
        src.append(np.asarray(dr.gather(mi.UInt, shots.src_indices, lanes), dtype=np.uint32))
        offset += len(pick)
    pad = k - used
    o.append(np.repeat(origin[:1], pad, axis=0) if a else np.zeros((pad, 3), np.float32))
    d_.append(np.tile(np.array([0.0, 0.0, 1.0], dtype=np.float32), (pad, 1)))
    k_tx.append(d_[-1])
    chain.append(np.zeros(pad, bool))
    loc.append(np.zeros(pad, np.uint32))
    h0.append(np.zeros(pad, np.uint64))
    h1.append(np.zeros(pad, np.uint64))
    start.append(np.full(pad, max_depth + 1, np.uint32))
    src.append(np.zeros(pad, np.uint32))

    def vec(cls, parts):
        x = np.concatenate(parts)
        return cls(*(_array(mi.Float, np.ascontiguousarray(x[:, i])) for i in range(3)))

    out.k_tx = vec(mi.Vector3f, k_tx)
    out.src_indices = _array(mi.UInt, np.concatenate(src))
    out.wedges, out.diffraction_depth = wedges, diffraction_depth
    state = {"ray": mi.Ray3f(vec(mi.Point3f, o), vec(mi.Vector3f, d_)),
             "specular_chain": _array(mi.Bool, np.concatenate(chain)),
             "hashes": [_array(mi.UInt64, np.concatenate(h0)), _array(mi.UInt64, np.concatenate(h1))],
             "active": dr.full(mi.Mask, True, k), "loc_en_inter": _array(mi.UInt, np.concatenate(loc)),
             "touched": dr.full(mi.Bool, False, k)}
    internals.sampler(gen).seed(seed, k)
    _bounce_in_one_loop(gen, mi_scene, out, state, max_depth, flags, movers,
                        start=_array(mi.UInt, np.concatenate(start)))
    return out


def _group_chains(record: dict) -> None:
    """Groups a depth's live specular-chain rays by chain (first hash), rays in ascending
    order within a group; lists the diffuse rays (numpy, for :func:`_connect`)."""
    import numpy as np

    h0 = np.asarray(record["hashes"][0]).astype(np.uint64)
    chain = np.flatnonzero(np.asarray(record["specular_chain"], dtype=bool))
    grouped = chain[np.argsort(h0[chain], kind="stable")]
    hs = h0[grouped]
    starts = np.flatnonzero(np.r_[True, hs[1:] != hs[:-1]]) if len(hs) else np.zeros(0, dtype=np.int64)
    record["grouped"], record["starts"] = grouped, starts
    record["sizes"] = np.diff(np.r_[starts, len(grouped)])
    record["diffuse_rays"] = np.flatnonzero(np.asarray(record["diffuse"], dtype=bool))
    record["h0"], record["h1"] = h0, np.asarray(record["hashes"][1]).astype(np.uint64)
    record["lanes"] = np.asarray(record["lane"], dtype=np.int64)  # (numpy, for _blocked_from and _connect)
    for key in ("diffuse", "specular_chain", "hashes"):  # grouped above: not needed any more
        del record[key]


class _SampleView:
    """The ``SampleData`` interface over the recorded shoot phase, for chosen rays
    (``lane``: indices of rays) at one depth: what ``PathsBuffer.add_paths`` reads."""

    def __init__(self, shots: _Shots, depth: int, lane):
        dr, mi = _jit()
        from caviar_plugins.radio import sionna_internals as internals

        WedgeGeometry = internals.ray_utilities()[1]
        self._shots, self.lane = shots, lane
        self._fields = internals.sample_data_fields()
        self._src = dr.gather(mi.UInt, shots.src_indices, lane)
        self._wedges = None
        if shots.wedges is not None:
            d = dr.gather(mi.UInt, shots.diffraction_depth, lane)
            seen = (d > 0) & (d <= depth)
            self._wedges = dr.select(seen, dr.gather(WedgeGeometry, shots.wedges, lane),
                                     WedgeGeometry.build_with_size(dr.width(lane)))

    def get(self, depth, active):
        dr, mi = _jit()

        index = (depth - 1) * dr.opaque(mi.UInt, self._shots.width) + self.lane
        data = dr.gather(self._fields, self._shots.samples, index, active)
        return data.interaction_type, data.shape, data.primitive, data.vertex, data.prob

    @property
    def diffracting_wedges(self):
        return self._wedges

    @property
    def src_indices(self):
        return self._src


def _visibility(mi_scene, rec: dict, tgt_positions, rays, targets):
    """Whether each target sees each ray's hit point (Sionna's test: a ray from the hit
    point, offset along its normal, to the target), and the direction of arrival."""
    import numpy as np

    dr, mi = _jit()
    j, t = _array(mi.UInt, rays.astype(np.uint32)), _array(mi.UInt, targets.astype(np.uint32))
    si = dr.zeros(mi.SurfaceInteraction3f, len(rays))
    si.p, si.n = dr.gather(mi.Point3f, rec["p"], j), dr.gather(mi.Normal3f, rec["n"], j)
    ray = si.spawn_ray_to(dr.gather(mi.Point3f, tgt_positions, t))
    visible = ~mi_scene.ray_test(ray)
    side = dr.dot(si.n, ray.d) > 0.0
    direction = mi.Vector3f(ray.d)
    dr.eval(visible, side, direction)
    return np.asarray(visible, dtype=bool), np.asarray(side, dtype=bool), direction


BEHIND_COS = -1e-3
"""A target is behind a reflecting surface when the cosine between the surface's normal
(towards the incident side) and the direction to the target is below this: about 0.06°
beyond the plane, so that rounding never decides."""


def _behind_reflections(shots: _Shots, depth: int, rec: dict, tgt_positions, rays):
    """For each of ``rays`` (indices into a depth's record) and each target: whether the
    ray's interaction there is a specular reflection and the target lies behind the
    reflecting plane, (rays, targets) bool; None when none of ``rays`` reflects. No
    specular path ends on that reflection with that target (the image method finds no
    reflection point between a target and its mirror image on the same side), so such a
    pair need not be tested for visibility: with 10 targets, 98 % of those tests see
    nothing, and about half of them are behind. Refraction, diffraction and diffuse
    ends are never culled, nor chains with a diffraction before the reflection.

    The side is the one the recorded ray came from. That is exact at the first bounce
    (the wave comes from the transmitter); later, the image method moves the previous
    vertex within its triangle, which stays on that side unless the triangle crosses the
    reflecting plane: meshes whose faces meet but do not cross (buildings on the ground)
    keep it. Checked against unculled solves in tests/test_shoot_cache.py and on the
    10-UAV SAR route (benches/bench_perf_steps.py: ``cull_vs_without``)."""
    import numpy as np

    from caviar_plugins.radio import sionna_internals as internals

    dr, mi = _jit()
    InteractionType = internals.ray_utilities()[0]
    j = _array(mi.UInt, rays.astype(np.uint32))
    lane = dr.gather(mi.UInt, rec["lane"], j)
    kinds = shots.samples.interaction_type
    index = dr.opaque(mi.UInt, (depth - 1) * shots.width) + lane
    reflects = np.asarray(dr.gather(type(kinds), kinds, index)) == int(InteractionType.SPECULAR)
    if shots.diffraction_depth is not None:
        # After a diffraction the path's previous vertex is a point of an edge, which the
        # image method moves along it: the edge may lie in the reflecting plane or cross
        # it, so the side the wave comes from is not the recorded one (seen on the SAR
        # route: a diffraction-reflection path lost). Such chains are always tested.
        diffracted = np.asarray(dr.gather(mi.UInt, shots.diffraction_depth, lane))
        reflects &= ~((diffracted > 0) & (diffracted < depth))
    if not reflects.any():
        return None
    p = np.asarray(dr.gather(mi.Point3f, rec["p"], j))  # (3, rays)
    n = np.asarray(dr.gather(mi.Normal3f, rec["n"], j))
    d = np.asarray(tgt_positions)[:, None, :] - p[:, :, None]  # (3, rays, targets)
    cos = np.einsum("ir,irt->rt", n, d) / np.maximum(np.sqrt(np.einsum("irt,irt->rt", d, d)), 1e-12)
    return reflects[:, None] & (cos < BEHIND_COS)


def _first_visible(mi_scene, rec: dict, tgt_positions, num_targets: int,
                   behind: Callable | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """For every (target, chain) pair of a depth, the first ray of the chain's group (in
    ray order) whose hit point the target sees, or -1; with the pairs' targets and the
    number of visibility tests made. Tested in rounds that double the
    rays tried per unresolved pair (1, 2, 4, ...): a chain seen by its first ray costs
    one test instead of one per ray. ``behind(rays)`` (optional, :func:`_behind_reflections`)
    names the (ray, target) pairs that cannot end a path: asked for each group's first ray,
    it rules out the group for that target, without a test."""
    grouped, starts, sizes = rec["grouped"], rec["starts"], rec["sizes"]
    g = len(starts)
    pair_group = np.tile(np.arange(g), num_targets)
    pair_target = np.repeat(np.arange(num_targets), g)
    first = np.full(g * num_targets, -1, dtype=np.int64)
    tried = np.zeros(g * num_targets, dtype=np.int64)
    todo = np.arange(g * num_targets)
    if behind is not None and g:
        # A group's rays share the chain, hence its last plane: which side of that plane
        # a target is on is the same for each, so the group's first ray decides.
        cut = behind(grouped[starts])  # (groups, targets)
        if cut is not None:
            todo = todo[~cut.T.reshape(-1)]  # pairs are target-major
    r = made = 0
    while len(todo):
        count = np.minimum(1 << r, sizes[pair_group[todo]] - tried[todo])
        flat = np.repeat(todo, count)
        made += len(flat)
        offset = np.arange(len(flat)) - np.repeat(np.cumsum(count) - count, count)
        pos = tried[flat] + offset
        visible, _, _ = _visibility(mi_scene, rec, tgt_positions, grouped[starts[pair_group[flat]] + pos],
                                    pair_target[flat])
        big = np.iinfo(np.int64).max
        best = np.minimum.reduceat(np.where(visible, pos, big), np.cumsum(count) - count)
        found = best < big
        first[todo[found]] = grouped[starts[pair_group[todo[found]]] + best[found]]
        tried[todo] += count
        todo = todo[~found & (tried[todo] < sizes[pair_group[todo]])]
        r += 1
    return first, pair_target, made


def _connect(shots: _Shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src: int,
             cull_behind: bool = True, blocked: np.ndarray | None = None) -> int:
    """Sionna's inner loop over targets, depth by depth, with exact deduplication:
    specular chains are grouped by hash, and a (chain, target) pair is stored from the
    first ray of the chain that sees the target, in ray order. Sionna's rule for its two
    hashes (round, floor) is kept: a chain is new if neither hash was stored before for
    that target. No table, so no collisions. ``blocked`` (:func:`_blocked_from`): a diffuse
    ray at depth d whose lane has a segment before d blocked ends no path. Returns the
    visibility tests made."""
    dr, mi = _jit()
    num_targets = dr.shape(tgt_positions)[1]
    mix = np.uint64(0x9E3779B97F4A7C15)
    made = 0
    for depth, rec in enumerate(shots.depths, start=1):
        if dr.width(rec["lane"]) == 0:  # (aimed rays: none has touched a moving object yet)
            continue
        behind = functools.partial(_behind_reflections, shots, depth, rec, tgt_positions) if cull_behind else None
        first, pair_target, tests = _first_visible(mi_scene, rec, tgt_positions, num_targets, behind)
        made += tests
        hit = first >= 0
        rays, targets = first[hit], pair_target[hit]
        order = np.lexsort((rays, targets))
        rays, targets = rays[order], targets[order]
        # Each stored ray has a first hash of its own (one per group and target); of rays
        # sharing a second hash, the first in order is new. Chains of different depths
        # hash different numbers of interactions: they meet only by a 64-bit collision,
        # so the sets of seen hashes are kept per depth.
        with np.errstate(over="ignore"):
            k1 = rec["h1"][rays] ^ (targets.astype(np.uint64) * mix)
        _, once = np.unique(k1, return_index=True)
        new1 = np.zeros(len(k1), dtype=bool)
        new1[once] = True
        chain_rays, chain_targets = rays[new1], targets[new1]
        # Diffuse rays: every one the target sees on its side ends a valid path.
        diffuse = rec["diffuse_rays"]
        if blocked is not None and len(diffuse):
            diffuse = diffuse[blocked[rec["lanes"][diffuse]] >= depth]
        d_rays = np.tile(diffuse, num_targets)
        d_targets = np.repeat(np.arange(num_targets), len(diffuse))
        if len(d_rays):
            made += len(d_rays)
            visible, side, _ = _visibility(mi_scene, rec, tgt_positions, d_rays, d_targets)
            keep = visible & side
            d_rays, d_targets = d_rays[keep], d_targets[keep]
        all_rays = np.r_[chain_rays, d_rays]
        all_targets = np.r_[chain_targets, d_targets]
        valid_np = np.r_[np.zeros(len(chain_rays), dtype=bool), np.ones(len(d_rays), dtype=bool)]
        if len(all_rays) == 0:
            continue
        order = np.lexsort((all_rays, all_targets))
        all_rays, all_targets, valid_np = all_rays[order], all_targets[order], valid_np[order]
        _, _, direction = _visibility(mi_scene, rec, tgt_positions, all_rays, all_targets)
        view = _SampleView(shots, depth, dr.gather(mi.UInt, rec["lane"], _array(mi.UInt, all_rays.astype(np.uint32))))
        store = dr.full(mi.Bool, True, len(all_rays))
        per_source = dr.scatter_inc(counter, view.src_indices, store)
        dr.eval(per_source)
        store &= per_source < max_num_paths_per_src
        path_ind = dr.scatter_inc(paths.paths_counter, mi.UInt(0), store)
        dr.eval(path_ind)
        k_tx = dr.gather(mi.Vector3f, shots.k_tx, view.lane)
        paths.add_paths(mi.UInt(depth), path_ind, view, _array(mi.Bool, valid_np),
                        _array(mi.UInt, all_targets.astype(np.uint32)),
                        k_tx, -direction, store)
        paths.schedule()
        dr.eval(counter)
    return made
