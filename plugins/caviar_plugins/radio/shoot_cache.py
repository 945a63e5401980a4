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
  ray of a packet until the last one dies).

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

from collections.abc import Callable, Hashable, Sequence
from typing import Any

import numpy as np


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
    the scene objects that move from solve to solve (UAV bodies) and that the fingerprint
    leaves out: the bounces are recorded with them moved out of the way, and each solve's
    visibility tests (and the image method after it) run in the scene with them where they
    are, so the paths they block are dropped; paths that reflect or diffract on them are
    not found (see the module docstring).
    """

    def __init__(self, generator: Any, fingerprint: Callable[[], Hashable],
                 movers: Callable[[], Sequence[Any]] | None = None, scene: Any = None):
        self.generator = generator
        self.fingerprint = fingerprint
        self.movers = movers
        self.scene = scene
        self.rays_per_moving_object = RAYS_PER_MOVING_OBJECT
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
        if self._key != key:
            moving = list(self.movers()) if self.movers is not None else []
            with internals.objects_out_of_the_way(self.scene, moving):
                self._shots = _shoot(self.generator, mi_scene, src_positions, samples_per_src, max_depth, flags,
                                     seed)
            self._key = key
            self.shoots += 1
        shots = self._shots
        assert shots is not None
        num_sources = dr.shape(src_positions)[1]
        paths = internals.new_paths_buffer(max_num_paths_per_src * num_sources, max_depth, diffraction)
        counter = dr.zeros(mi.UInt, num_sources)
        if los:
            internals.add_line_of_sight(self.generator, mi_scene, src_positions, tgt_positions, paths, counter)
        _connect(shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src)
        moving = list(self.movers()) if self.movers is not None else []
        if moving:
            # Paths by way of the moving objects: rays aimed at each one's bounding sphere,
            # bounced in the scene as it is now, connected from the first hit on one of them.
            boxes = np.array([[np.array(o.mi_mesh.bbox().min), np.array(o.mi_mesh.bbox().max)] for o in moving],
                             dtype=float).reshape(-1, 2, 3)
            source = np.array(dr.ravel(src_positions).numpy(), dtype=float)[:3]
            aimed = np.concatenate([aim_at(source, box.mean(axis=0), np.linalg.norm(box[1] - box[0]) / 2,
                                           self.rays_per_moving_object) for box in boxes])
            local = _shoot(self.generator, mi_scene, src_positions, 0, max_depth,
                           (specular_reflection, False, refraction, diffraction, edge_diffraction), seed,
                           aimed=aimed, touch_boxes=boxes + [[-MARGIN_M], [MARGIN_M]])
            _connect(local, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src)
        self.paths_counter_per_source = counter
        self.connects += 1
        return paths


RAYS_PER_MOVING_OBJECT = 4096
"""Rays aimed at each moving object's bounding sphere per solve (about 5 cm apart on a
2 m UAV body, against about 1.3 m for 3e5 rays over the whole sphere at 200 m)."""
MARGIN_M = 0.01
"""A hit within this distance of a moving object's bounding box counts as a hit on it."""


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


def _shoot(gen, mi_scene, src_positions, samples_per_src: int, max_depth: int, flags, seed: int,
           aimed=None, touch_boxes=None) -> _Shots:
    """Sionna's bounce loop, one wavefront per depth, without the targets.

    ``aimed`` (directions, an (n, 3) array, from the single source): these rays instead of
    Sionna's Fibonacci lattice. ``touch_boxes`` ((B, 2, 3): min and max corners): a ray is
    kept for the connect phase only from the depth at which it first hit inside a box."""
    dr, mi = _jit()
    from caviar_plugins.radio import sionna_internals as internals

    InteractionType, WedgeGeometry, fibonacci_lattice, hash_fnv1a, spawn_ray_from_sources = \
        internals.ray_utilities()
    sample_fields = internals.sample_data_fields()
    plane_hashers, edge_hashers = internals.hashers(gen)

    specular_on, diffuse_on, refraction_on, diffraction_on, edge_diffraction_on = flags
    num_sources = dr.shape(src_positions)[1]
    if aimed is not None:
        samples_per_src = len(aimed)
    n = samples_per_src * num_sources
    shots = _Shots()
    sampler = internals.sampler(gen)
    sampler.seed(seed, n)
    shots.width = n
    shots.samples = dr.zeros(sample_fields, n * max(1, max_depth))
    shots.src_indices = internals.source_index_per_sample(num_sources, samples_per_src)
    ray = spawn_ray_from_sources(fibonacci_lattice, samples_per_src, src_positions)
    if aimed is not None:
        ray.d = mi.Vector3f(*(mi.Float(aimed[:, i].astype(np.float32)) for i in range(3)))
    touched = dr.full(mi.Bool, touch_boxes is None, n)
    shots.k_tx = dr.copy(ray.d)
    specular_chain = dr.full(mi.Bool, True, n)
    hashes = [dr.zeros(mi.UInt64, n) for _ in plane_hashers]
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
        s, normal, wedges = internals.sample_radio_material(gen, si, ray.o, ray.d, sample1, sample2,
                                                            sample2_diffraction, loc_en_inter, diffraction_on,
                                                            edge_diffraction_on, active)
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
        fields = sample_fields(
            dr.select(active, int_type, 0), dr.select(active, dr.reinterpret_array(mi.UInt, si.shape), 0),
            dr.select(active, si.prim_index, 0), dr.select(active, si.p, mi.Point3f(0.0)),
            dr.select(active, s.pdf, 0.0))
        dr.scatter(shots.samples, fields, (depth - 1) * n + lane)
        if diffraction_on:
            shots.wedges = dr.select(diffraction, wedges, shots.wedges)
            shots.diffraction_depth = dr.select(diffraction, depth, shots.diffraction_depth)
        for i in range(len(hashes)):
            plane_hash = plane_hashers[i](si.n, si.p)
            edge_hash = edge_hashers[i](wedges.o, wedges.o + wedges.e_hat * wedges.length)
            inter_hash = dr.select(int_type == InteractionType.SPECULAR, plane_hash, int_type)
            inter_hash = dr.select(int_type == InteractionType.DIFFRACTION, edge_hash, inter_hash)
            hashes[i] = hash_fnv1a(inter_hash, h=hashes[i])
        if touch_boxes is not None:
            for lo, hi in touch_boxes:  # opaque: the boxes move every solve, the kernels stay
                low, high = (dr.opaque(mi.Point3f, [float(x) for x in c]) for c in (lo, hi))
                touched |= active & dr.all((si.p >= low) & (si.p <= high))
        alive = dr.compress(active & touched)
        record = {"lane": alive, "p": dr.gather(mi.Point3f, si.p, alive), "n": dr.gather(mi.Normal3f, normal, alive),
                  "diffuse": dr.gather(mi.Bool, diffuse, alive),
                  "specular_chain": dr.gather(mi.Bool, specular_chain, alive),
                  "hashes": [dr.gather(mi.UInt64, h, alive) for h in hashes]}
        ray = si.spawn_ray(d=k_world)
        specular_chain |= diffuse
        sampler.schedule_state()
        state = [record, shots.samples, ray, specular_chain, hashes, active, loc_en_inter, shots.wedges,
                 shots.diffraction_depth, touched]
        dr.eval(*[x for x in state if x is not None])
        _group_chains(record)
        shots.depths.append(record)
        if dr.width(dr.compress(active)) == 0:
            break
    return shots


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


def _visibility(mi_scene, rec: dict, tgt_positions, rays, targets):
    """Whether each target sees each ray's hit point (Sionna's test: a ray from the hit
    point, offset along its normal, to the target), and the direction of arrival."""
    import numpy as np

    dr, mi = _jit()
    j, t = mi.UInt(rays.astype(np.uint32)), mi.UInt(targets.astype(np.uint32))
    si = dr.zeros(mi.SurfaceInteraction3f, len(rays))
    si.p, si.n = dr.gather(mi.Point3f, rec["p"], j), dr.gather(mi.Normal3f, rec["n"], j)
    ray = si.spawn_ray_to(dr.gather(mi.Point3f, tgt_positions, t))
    visible = ~mi_scene.ray_test(ray)
    side = dr.dot(si.n, ray.d) > 0.0
    direction = mi.Vector3f(ray.d)
    dr.eval(visible, side, direction)
    return np.asarray(visible, dtype=bool), np.asarray(side, dtype=bool), direction


def _first_visible(mi_scene, rec: dict, tgt_positions, num_targets: int):
    """For every (target, chain) pair of a depth, the first ray of the chain's group (in
    ray order) whose hit point the target sees, or -1. Tested in rounds that double the
    rays tried per unresolved pair (1, 2, 4, ...): a chain seen by its first ray costs
    one test instead of one per ray."""
    import numpy as np

    grouped, starts, sizes = rec["grouped"], rec["starts"], rec["sizes"]
    g = len(starts)
    pair_group = np.tile(np.arange(g), num_targets)
    pair_target = np.repeat(np.arange(num_targets), g)
    first = np.full(g * num_targets, -1, dtype=np.int64)
    tried = np.zeros(g * num_targets, dtype=np.int64)
    todo = np.arange(g * num_targets)
    r = 0
    while len(todo):
        count = np.minimum(1 << r, sizes[pair_group[todo]] - tried[todo])
        flat = np.repeat(todo, count)
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
    return first, pair_target


def _connect(shots: _Shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src: int) -> None:
    """Sionna's inner loop over targets, depth by depth, with exact deduplication:
    specular chains are grouped by hash, and a (chain, target) pair is stored from the
    first ray of the chain that sees the target, in ray order. Sionna's rule for its two
    hashes (round, floor) is kept: a chain is new if neither hash was stored before for
    that target. No table, so no collisions."""
    import numpy as np

    dr, mi = _jit()
    num_targets = dr.shape(tgt_positions)[1]
    mix = np.uint64(0x9E3779B97F4A7C15)
    for depth, rec in enumerate(shots.depths, start=1):
        if dr.width(rec["lane"]) == 0:  # (aimed rays: none has touched a moving object yet)
            continue
        first, pair_target = _first_visible(mi_scene, rec, tgt_positions, num_targets)
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
        d_rays = np.tile(diffuse, num_targets)
        d_targets = np.repeat(np.arange(num_targets), len(diffuse))
        if len(d_rays):
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
        view = _SampleView(shots, depth, dr.gather(mi.UInt, rec["lane"], mi.UInt(all_rays.astype(np.uint32))))
        store = dr.full(mi.Bool, True, len(all_rays))
        per_source = dr.scatter_inc(counter, view.src_indices, store)
        dr.eval(per_source)
        store &= per_source < max_num_paths_per_src
        path_ind = dr.scatter_inc(paths.paths_counter, mi.UInt(0), store)
        dr.eval(path_ind)
        k_tx = dr.gather(mi.Vector3f, shots.k_tx, view.lane)
        paths.add_paths(mi.UInt(depth), path_ind, view, mi.Bool(valid_np), mi.UInt(all_targets.astype(np.uint32)),
                        k_tx, -direction, store)
        paths.schedule()
        dr.eval(counter)
