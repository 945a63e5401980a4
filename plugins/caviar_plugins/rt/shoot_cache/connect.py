"""The connect phase: every solve, the targets' visibility from the recorded rays' hit
points, Sionna's specular-chain deduplication (exact here), and the paths stored in
Sionna's path buffer.

Per depth (:func:`connect`): the first ray of each chain group that a target sees, tried
in rounds that double the rays per unresolved pair (:func:`first_visible`), a target behind
a chain's last reflecting plane ruled out without a test (:func:`behind_reflections`), every
diffuse ray the target sees on its side, and Sionna's ``PathsBuffer.add_paths`` over a view
of the recorded sample data (:class:`SampleView`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.drjit_setup import aligned_array, jit
from caviar_plugins.rt.shoot_cache.records import DepthRecord, Shots


class SampleView:
    """The ``SampleData`` interface over the recorded shoot phase, for chosen rays
    (``lane``: indices of rays) at one depth: what ``PathsBuffer.add_paths`` reads."""

    def __init__(self, shots: Shots, depth: int, lane):
        dr, mi = jit()
        WedgeGeometry = adapter.ray_utilities()[1]
        self._shots, self.lane = shots, lane
        self._fields = adapter.sample_data_fields()
        self._src = dr.gather(mi.UInt, shots.src_indices, lane)
        self._wedges = None
        if shots.wedges is not None:
            d = dr.gather(mi.UInt, shots.diffraction_depth, lane)
            seen = (d > 0) & (d <= depth)
            self._wedges = dr.select(seen, dr.gather(WedgeGeometry, shots.wedges, lane),
                                     WedgeGeometry.build_with_size(dr.width(lane)))

    def get(self, depth, active):
        dr, mi = jit()

        index = (depth - 1) * dr.opaque(mi.UInt, self._shots.width) + self.lane
        data = dr.gather(self._fields, self._shots.samples, index, active)
        return data.interaction_type, data.shape, data.primitive, data.vertex, data.prob

    @property
    def diffracting_wedges(self):
        return self._wedges

    @property
    def src_indices(self):
        return self._src


def visibility(mi_scene, rec: DepthRecord, tgt_positions, rays, targets):
    """Whether each target sees each ray's hit point (Sionna's test: a ray from the hit
    point, offset along its normal, to the target), and the direction of arrival."""
    dr, mi = jit()
    j, t = aligned_array(mi.UInt, rays.astype(np.uint32)), aligned_array(mi.UInt, targets.astype(np.uint32))
    si = dr.zeros(mi.SurfaceInteraction3f, len(rays))
    si.p, si.n = dr.gather(mi.Point3f, rec.p, j), dr.gather(mi.Normal3f, rec.n, j)
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


def behind_reflections(shots: Shots, depth: int, rec: DepthRecord, tgt_positions, rays):
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
    dr, mi = jit()
    InteractionType = adapter.ray_utilities()[0]
    j = aligned_array(mi.UInt, rays.astype(np.uint32))
    lane = dr.gather(mi.UInt, rec.lane, j)
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
    p = np.asarray(dr.gather(mi.Point3f, rec.p, j))  # (3, rays)
    n = np.asarray(dr.gather(mi.Normal3f, rec.n, j))
    d = np.asarray(tgt_positions)[:, None, :] - p[:, :, None]  # (3, rays, targets)
    cos = np.einsum("ir,irt->rt", n, d) / np.maximum(np.sqrt(np.einsum("irt,irt->rt", d, d)), 1e-12)
    return reflects[:, None] & (cos < BEHIND_COS)


def first_visible(mi_scene, rec: DepthRecord, tgt_positions, num_targets: int,
                   behind: Callable | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """For every (target, chain) pair of a depth, the first ray of the chain's group (in
    ray order) whose hit point the target sees, or -1; with the pairs' targets and the
    number of visibility tests made. Tested in rounds that double the
    rays tried per unresolved pair (1, 2, 4, ...): a chain seen by its first ray costs
    one test instead of one per ray. ``behind(rays)`` (optional, :func:`behind_reflections`)
    names the (ray, target) pairs that cannot end a path: asked for each group's first ray,
    it rules out the group for that target, without a test."""
    grouped, starts, sizes = rec.grouped, rec.starts, rec.sizes
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
        visible, _, _ = visibility(mi_scene, rec, tgt_positions, grouped[starts[pair_group[flat]] + pos],
                                    pair_target[flat])
        big = np.iinfo(np.int64).max
        best = np.minimum.reduceat(np.where(visible, pos, big), np.cumsum(count) - count)
        found = best < big
        first[todo[found]] = grouped[starts[pair_group[todo[found]]] + best[found]]
        tried[todo] += count
        todo = todo[~found & (tried[todo] < sizes[pair_group[todo]])]
        r += 1
    return first, pair_target, made


def connect(shots: Shots, mi_scene, tgt_positions, paths, counter, max_num_paths_per_src: int,
             cull_behind: bool = True, blocked: np.ndarray | None = None) -> int:
    """Sionna's inner loop over targets, depth by depth, with exact deduplication:
    specular chains are grouped by hash, and a (chain, target) pair is stored from the
    first ray of the chain that sees the target, in ray order. Sionna's rule for its two
    hashes (round, floor) is kept: a chain is new if neither hash was stored before for
    that target. No table, so no collisions. ``blocked`` (:func:`blocked_from`): a diffuse
    ray at depth d whose lane has a segment before d blocked ends no path. Returns the
    visibility tests made."""
    dr, mi = jit()
    num_targets = dr.shape(tgt_positions)[1]
    mix = np.uint64(0x9E3779B97F4A7C15)
    made = 0
    for depth, rec in enumerate(shots.depths, start=1):
        if rec.size == 0:  # (aimed rays: none has touched a moving object yet)
            continue
        behind = functools.partial(behind_reflections, shots, depth, rec, tgt_positions) if cull_behind else None
        first, pair_target, tests = first_visible(mi_scene, rec, tgt_positions, num_targets, behind)
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
            k1 = rec.h1[rays] ^ (targets.astype(np.uint64) * mix)
        _, once = np.unique(k1, return_index=True)
        new1 = np.zeros(len(k1), dtype=bool)
        new1[once] = True
        chain_rays, chain_targets = rays[new1], targets[new1]
        # Diffuse rays: every one the target sees on its side ends a valid path.
        diffuse = rec.diffuse_rays
        if blocked is not None and len(diffuse):
            diffuse = diffuse[blocked[rec.lanes[diffuse]] >= depth]
        d_rays = np.tile(diffuse, num_targets)
        d_targets = np.repeat(np.arange(num_targets), len(diffuse))
        if len(d_rays):
            made += len(d_rays)
            visible, side, _ = visibility(mi_scene, rec, tgt_positions, d_rays, d_targets)
            keep = visible & side
            d_rays, d_targets = d_rays[keep], d_targets[keep]
        all_rays = np.r_[chain_rays, d_rays]
        all_targets = np.r_[chain_targets, d_targets]
        valid_np = np.r_[np.zeros(len(chain_rays), dtype=bool), np.ones(len(d_rays), dtype=bool)]
        if len(all_rays) == 0:
            continue
        order = np.lexsort((all_rays, all_targets))
        all_rays, all_targets, valid_np = all_rays[order], all_targets[order], valid_np[order]
        _, _, direction = visibility(mi_scene, rec, tgt_positions, all_rays, all_targets)
        picked = aligned_array(mi.UInt, all_rays.astype(np.uint32))
        view = SampleView(shots, depth, dr.gather(mi.UInt, rec.lane, picked))
        store = dr.full(mi.Bool, True, len(all_rays))
        per_source = dr.scatter_inc(counter, view.src_indices, store)
        dr.eval(per_source)
        store &= per_source < max_num_paths_per_src
        path_ind = dr.scatter_inc(paths.paths_counter, mi.UInt(0), store)
        dr.eval(path_ind)
        k_tx = dr.gather(mi.Vector3f, shots.k_tx, view.lane)
        paths.add_paths(mi.UInt(depth), path_ind, view, aligned_array(mi.Bool, valid_np),
                        aligned_array(mi.UInt, all_targets.astype(np.uint32)),
                        k_tx, -direction, store)
        paths.schedule()
        dr.eval(counter)
    return made
