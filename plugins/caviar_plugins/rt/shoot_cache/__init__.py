"""Shoot once, connect every step: Sionna RT's shoot-and-bounce split in two phases.

The phases live in modules of their own, as Sionna RT's ``path_solvers`` do, and hand each
other typed records (:mod:`~caviar_plugins.rt.shoot_cache.records`):
:mod:`~caviar_plugins.rt.shoot_cache.shoot` records the bounces,
:mod:`~caviar_plugins.rt.shoot_cache.movers` adds the moving objects on top of them, and
:mod:`~caviar_plugins.rt.shoot_cache.connect` tests the targets and stores the paths.

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
  reflection is not tested: no specular path ends there
  (:func:`~caviar_plugins.rt.shoot_cache.connect.behind_reflections`); Sionna tests it and the
  image method drops the candidate.

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

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.drjit_setup import jit
from caviar_plugins.rt.scene import bounding_box, objects_out_of_the_way, shape_table
from caviar_plugins.rt.shoot_cache import connect, shoot
from caviar_plugins.rt.shoot_cache.movers import (
    RAYS_PER_MOVING_OBJECT,
    aim_at,
    blocked_from,
    boxes_scene,
    by_way_of_movers,
    first_rays_met,
    met_by_movers,
)
from caviar_plugins.rt.shoot_cache.records import Shots


class ShootCache:
    """A drop-in for the solver's candidate generator (see the module docstring); every
    Sionna internal it uses goes through :mod:`caviar_plugins.rt.sionna_adapter`.

    ``fingerprint()`` returns a hashable description of everything but the targets that
    the bounces depend on; :class:`~caviar_plugins.rt.scene.MovingObjects` supplies one. ``movers()`` (optional) returns
    the scene objects that move from solve to solve (UAV bodies, vehicles) and that the
    fingerprint leaves out: the bounces are recorded with them moved out of the way, and each
    solve's visibility tests (and the image method after it) run in the scene with them where
    they are, so the paths they block are dropped; the paths by way of them come from rays
    aimed at each (``rays_for(obj)`` of them, :data:`RAYS_PER_MOVING_OBJECT` without it; None:
    Sionna's own rays from the source that now meet it first, :func:`first_rays_met`; 0: none,
    for an object parked out of the scene) and from the recorded rays that now meet one after
    a bounce (see :func:`by_way_of_movers`). ``boxes_of(obj)`` (optional) gives the bounds
    (m, 2, 3) of an object's separate bodies (a pool of boxes in one mesh), each then aimed at
    and prefiltered on its own; without it, the object's bounding box.
    """

    cull_behind = True
    """Whether targets behind a chain's last reflecting plane go untested
    (:func:`behind_reflections`); False tests them as Sionna does, for comparison."""

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
        self._shots: Shots | None = None
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
    def shots(self) -> Shots | None:
        """The recorded shoot phase that serves the solves (None before one is recorded)."""
        return self._shots

    @property
    def has_seen_geometry(self) -> bool:
        """Whether the last solve's geometry was seen, so that the next solve with it is
        served from the cache (a resumed run sees it once more before going on)."""
        return self._seen is not None

    def __call__(self, mi_scene, src_positions, tgt_positions, samples_per_src: int, max_num_paths_per_src: int,
                 max_depth: int, los: bool, specular_reflection: bool, diffuse_reflection: bool, refraction: bool,
                 diffraction: bool, edge_diffraction: bool, seed: int = 1, src_boxes=None):
        dr, mi = jit()
        flags = (specular_reflection, diffuse_reflection, refraction, diffraction, edge_diffraction)
        # More than one source (several transmitters, or synthetic_array = false): Sionna
        # deduplicates chains per source, this cache does not yet, so Sionna's loop runs (and
        # the scene is not fingerprinted for nothing).
        covered = src_boxes is None and max_depth > 0 and dr.shape(src_positions)[1] == 1
        key = (self.fingerprint(), id(mi_scene), tuple(dr.ravel(src_positions).numpy().tolist()), samples_per_src,
               max_depth, flags, seed) if covered else None
        if not covered or key != self._seen:
            # New geometry (or options this cache does not cover): Sionna's own loop.
            self._seen = key
            self._key = self._shots = None
            self.paths_counter_per_source = None
            return self.generator(mi_scene, src_positions, tgt_positions, samples_per_src, max_num_paths_per_src,
                                  max_depth, los, specular_reflection, diffuse_reflection, refraction, diffraction,
                                  edge_diffraction, seed, src_boxes)
        moving = list(self.movers()) if self.movers is not None else []
        if self._key != key or self._shots is None or (moving and not self._shots.keeps_state):
            with objects_out_of_the_way(self.scene, moving):
                self._shots = shoot.shoot(self.generator, mi_scene, src_positions, samples_per_src, max_depth, flags,
                                     seed, keep_state=bool(moving))
            self._key = key
            self.shoots += 1
        shots = self._shots
        assert shots is not None
        num_sources = dr.shape(src_positions)[1]
        paths = adapter.new_paths_buffer(max_num_paths_per_src * num_sources, max_depth, diffraction)
        counter = dr.zeros(mi.UInt, num_sources)
        if los:
            adapter.add_line_of_sight(self.generator, mi_scene, src_positions, tgt_positions, paths, counter)
        if not moving:
            self.visibility_tests += connect.connect(shots, mi_scene, tgt_positions, paths, counter,
                                                     max_num_paths_per_src, self.cull_behind)
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
            near = boxes_scene(present) if len(present) else None
            # Objects given no count (None): Sionna's own first rays (the recorded ones from the
            # source) that now meet one of them first (the boxes of all present objects
            # prefilter them; the shape table keeps those on these objects).
            own = [obj for obj, n in zip(moving, asked_per_object, strict=True) if n is None]
            first = first_rays_met(mi_scene, shots, source, shape_table(self.scene, own), near) if own \
                else np.zeros((0, 3))
            table = shape_table(self.scene, moving)
            picked = met_by_movers(mi_scene, shots, max_depth, table, near)
            # Sionna's image method re-checks the segments of specular chains, not of diffuse
            # paths: a diffuse path whose earlier segments now meet a moving object is dropped
            # here. And a ray goes on from the first moving object it meets only: a recorded
            # ray blocked before a later meeting is not continued from there.
            blocked = blocked_from(mi_scene, shots, source, table, near, picked)
            if blocked is not None:
                picked = [(d, pick[blocked[shots.depths[d - 1].lanes[pick]] == d]) for d, pick in picked]
                picked = [(d, pick) for d, pick in picked if len(pick)]
            self.visibility_tests += connect.connect(shots, mi_scene, tgt_positions, paths, counter,
                                                     max_num_paths_per_src, self.cull_behind, blocked)
            # Paths by way of the moving objects (see by_way_of_movers).
            more = by_way_of_movers(self.generator, mi_scene, shots, src_positions, max_depth, flags, seed,
                                     table, aimed, near, first, picked)
            if more is not None:
                self.visibility_tests += connect.connect(more, mi_scene, tgt_positions, paths, counter,
                                                         max_num_paths_per_src, self.cull_behind)
        self.paths_counter_per_source = counter
        self.connects += 1
        return paths


__all__ = ["RAYS_PER_MOVING_OBJECT", "ShootCache"]
