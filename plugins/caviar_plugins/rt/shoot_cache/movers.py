"""Moving objects on top of the recorded bounces: which recorded rays now meet a moving
object (UAV bodies, vehicles), and the rays that go on from one.

The bounces of the static scene are recorded with the moving objects out of the way
(:mod:`~caviar_plugins.rt.shoot_cache.shoot`). At each solve, a scene of nothing but the
objects' boxes (:func:`boxes_scene`) prefilters the recorded rays; those that meet a box are
cast again in the whole scene, and the ones whose first hit is on a moving object
(:func:`~caviar_plugins.rt.scene.shape_table`) go on from it (:func:`by_way_of_movers`), while the diffuse paths they
would have ended are dropped (:func:`blocked_from`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.drjit_setup import aligned_array, jit
from caviar_plugins.rt.scene import on_shapes
from caviar_plugins.rt.shoot_cache.records import RayState, Shots
from caviar_plugins.rt.shoot_cache.shoot import bounce_in_one_loop, enabled_interactions

RAYS_PER_MOVING_OBJECT = 4096
"""Rays aimed at each moving body's bounding sphere per solve (about 5 cm apart on a
2 m UAV body, against about 1.3 m for 3e5 rays over the whole sphere at 200 m)."""
PAD_RAYS = 1024
"""The rays by way of moving objects come in multiples of this (see :func:`by_way_of_movers`)."""


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


BOX_MARGIN_M = 0.01
"""How much the boxes of :func:`boxes_scene` stand out of the objects' bounding boxes."""

# Corners of the unit cube (corner i: x from bit 0, y from bit 1, z from bit 2) and its 12
# triangles, outward.
_CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
_CUBE_FACES = np.array([(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4), (2, 6, 7), (2, 7, 3),
                        (0, 4, 6), (0, 6, 2), (1, 3, 7), (1, 7, 5)], dtype=np.uint32)


def boxes_scene(boxes: np.ndarray) -> Any:
    """A Mitsuba scene of nothing but ``boxes`` ((m, 2, 3): each object's bounding box, grown
    by :data:`BOX_MARGIN_M`), one mesh: a ray that meets none of them meets none of the
    objects, and testing a few ten thousand rays against it costs well under a millisecond
    (a ray test in the whole scene, tens of milliseconds)."""
    dr, mi = jit()
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


def met_by_movers(mi_scene, shots: Shots, max_depth: int, movers, near) -> list[tuple[int, np.ndarray]]:
    """The recorded rays whose next segment now meets a moving object first, as (depth, indices
    into that depth's record): those that meet one of the objects' boxes (``near``,
    :func:`boxes_scene`; None: all parked, none) are cast again in the whole scene, and kept
    where the first shape hit is one of ``movers`` (:func:`~caviar_plugins.rt.scene.shape_table`)."""
    dr, mi = jit()
    picked = []
    for d, rec in enumerate(shots.depths[: max_depth - 1], start=1):
        if near is None or rec.size == 0 or not rec.goes_on:
            continue
        ahead = dr.compress(near.ray_test(mi.Ray3f(rec.o, rec.d)))
        if dr.width(ahead) == 0:
            continue
        # (Which shape is hit first is all that is needed: the preliminary intersection,
        # without the surface interaction's call into every shape of the scene, about 8 ms.)
        hit = mi_scene.ray_intersect_preliminary(mi.Ray3f(dr.gather(mi.Point3f, rec.o, ahead),
                                                          dr.gather(mi.Vector3f, rec.d, ahead)),
                                                 coherent=False)
        on = np.asarray(on_shapes(movers, hit), dtype=bool)
        pick = np.asarray(ahead, dtype=np.int64)[on]
        if len(pick):
            picked.append((d, pick))
    return picked


def source_lanes_met(mi_scene, shots: Shots, source: np.ndarray, table, near,
                     lanes: np.ndarray | None = None) -> np.ndarray:
    """The lanes (of ``lanes``; None: all) whose recorded ray from the source (Sionna's
    Fibonacci lattice, ``shots.k_tx``) now hits a shape that ``table`` marks first: those that
    meet one of the boxes of ``near`` (:func:`boxes_scene`, boxes around those shapes and
    maybe others) are cast again in the whole scene."""
    dr, mi = jit()
    origin = mi.Point3f(*(float(x) for x in source))
    if lanes is None:
        lanes = np.arange(shots.width, dtype=np.int64)
        k = shots.k_tx
    else:
        k = dr.gather(mi.Vector3f, shots.k_tx, aligned_array(mi.UInt, lanes.astype(np.uint32)))
    ahead = np.flatnonzero(np.asarray(near.ray_test(mi.Ray3f(origin, k)), dtype=bool))
    if len(ahead) == 0:
        return np.zeros(0, dtype=np.int64)
    d = dr.gather(mi.Vector3f, k, aligned_array(mi.UInt, ahead.astype(np.uint32)))
    on = np.asarray(on_shapes(table, mi_scene.ray_intersect_preliminary(mi.Ray3f(origin, d), coherent=False)),
                    dtype=bool)
    return lanes[ahead[on]]


def first_rays_met(mi_scene, shots: Shots, source: np.ndarray, table, near) -> np.ndarray:
    """The directions (m, 3) of the recorded rays from the source whose first hit is now on a
    shape that ``table`` marks (:func:`source_lanes_met`)."""
    dr, mi = jit()
    lanes = source_lanes_met(mi_scene, shots, source, table, near)
    d = dr.gather(mi.Vector3f, shots.k_tx, aligned_array(mi.UInt, lanes.astype(np.uint32)))
    return np.array(d, dtype=float).reshape(3, -1).T


NOT_BLOCKED = np.iinfo(np.int32).max


def blocked_from(mi_scene, shots: Shots, source: np.ndarray, movers, near,
                 picked: list[tuple[int, np.ndarray]]) -> np.ndarray | None:
    """Per lane of the recorded bounces, the first segment that now meets a moving object
    first (segment 0: source to first hit; segment d: the hit at depth d to the next), or
    :data:`NOT_BLOCKED`, for the lanes that end a diffuse path or meet a moving object
    after a bounce (``picked``, from :func:`met_by_movers`); None when there are none or no
    object is near. Segments d >= 1 come from ``picked``; segment 0 from
    :func:`source_lanes_met`."""
    dr, _ = jit()
    if near is None:
        return None
    asked = [rec.lanes[rec.diffuse_rays] for rec in shots.depths
             if rec.size and len(rec.diffuse_rays)]
    asked += [shots.depths[d - 1].lanes[pick] for d, pick in picked]
    if not asked:
        return None
    blocked = np.full(shots.width, NOT_BLOCKED, dtype=np.int64)
    for d, pick in reversed(picked):  # the earliest segment wins
        blocked[shots.depths[d - 1].lanes[pick]] = d
    blocked[source_lanes_met(mi_scene, shots, source, movers, near, np.unique(np.concatenate(asked)))] = 0
    return blocked


def by_way_of_movers(gen, mi_scene, shots: Shots, src_positions, max_depth: int, flags, seed: int, movers,
                     aimed: np.ndarray, near=None, first: np.ndarray | None = None,
                     picked: list[tuple[int, np.ndarray]] | None = None) -> Shots | None:
    """The rays that meet a moving object, bounced in the scene as it is now and connected
    from their first hit on one (one bounce loop for all, each ray setting off at its own
    depth):

    * ``aimed`` rays from the source at the objects (depth 1), for the paths that meet one
      first, with the diffuse branch off (their density is not Sionna's);
    * ``first``: Sionna's own rays from the source (directions) that meet one first
      (:func:`first_rays_met`), with every interaction Sionna's loop enables;
    * the rays of the recorded bounces that now meet one after a bounce on the static scene
      (Sionna's loop, run now, would send them onto it): each goes on from the depth at which
      it meets it, with the interactions it had before (``picked``: :func:`met_by_movers`'s
      answer, when the caller has it)."""
    dr, mi = jit()
    WedgeGeometry = adapter.ray_utilities()[1]
    sample_fields = adapter.sample_data_fields()
    if picked is None:
        picked = met_by_movers(mi_scene, shots, max_depth, movers, near)
    first = np.zeros((0, 3)) if first is None else first
    a = len(aimed) + len(first)
    used = a + sum(len(pick) for _, pick in picked)
    if used == 0:  # every moving object parked, none met: no paths by way of them
        return None
    # Padded to a multiple of PAD_RAYS with rays that never set off: Dr.Jit compiles the loop
    # anew for a new width, and the number of rays met varies from solve to solve.
    k = -(-used // PAD_RAYS) * PAD_RAYS
    out = Shots(width=k, samples=dr.zeros(sample_fields, k * max_depth))
    enabled, all_enabled = enabled_interactions(flags, diffuse=False), enabled_interactions(flags)
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
        idx = aligned_array(mi.UInt, pick.astype(np.uint32))
        lanes = dr.gather(mi.UInt, rec.lane, idx)
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
        o.append(np.array(dr.gather(mi.Point3f, rec.o, idx), dtype=np.float32).reshape(3, -1).T)
        d_.append(np.array(dr.gather(mi.Vector3f, rec.d, idx), dtype=np.float32).reshape(3, -1).T)
        k_tx.append(np.array(dr.gather(mi.Vector3f, shots.k_tx, lanes), dtype=np.float32).reshape(3, -1).T)
        chain.append(np.asarray(dr.gather(mi.Bool, rec.chain_next, idx), dtype=bool))
        loc.append(np.asarray(dr.gather(mi.UInt, rec.loc, idx), dtype=np.uint32))
        h0.append(rec.h0[pick])
        h1.append(rec.h1[pick])
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
        return cls(*(aligned_array(mi.Float, np.ascontiguousarray(x[:, i])) for i in range(3)))

    out.k_tx = vec(mi.Vector3f, k_tx)
    out.src_indices = aligned_array(mi.UInt, np.concatenate(src))
    out.wedges, out.diffraction_depth = wedges, diffraction_depth
    state = RayState(ray=mi.Ray3f(vec(mi.Point3f, o), vec(mi.Vector3f, d_)),
                     specular_chain=aligned_array(mi.Bool, np.concatenate(chain)),
                     hashes=[aligned_array(mi.UInt64, np.concatenate(h0)),
                             aligned_array(mi.UInt64, np.concatenate(h1))],
                     active=dr.full(mi.Mask, True, k), loc_en_inter=aligned_array(mi.UInt, np.concatenate(loc)),
                     touched=dr.full(mi.Bool, False, k))
    adapter.sampler(gen).seed(seed, k)
    bounce_in_one_loop(gen, mi_scene, out, state, max_depth, flags, movers,
                       start=aligned_array(mi.UInt, np.concatenate(start)))
    return out
