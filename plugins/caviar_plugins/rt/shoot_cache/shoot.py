"""The shoot phase: Sionna's bounce loop without the targets, recorded per depth.

:func:`shoot` runs it for the static scene, one wavefront per depth (:func:`bounce`);
:func:`bounce_in_one_loop` runs it as one Dr.Jit symbolic loop for the rays that meet
moving objects (:mod:`~caviar_plugins.rt.shoot_cache.movers`). Both call :func:`interact`
at each depth: Sionna's material and wedge sampling, random numbers and chain hashing.
"""

from __future__ import annotations

import numpy as np

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.drjit_setup import aligned_array, jit
from caviar_plugins.rt.scene import on_shapes
from caviar_plugins.rt.shoot_cache.records import DepthRecord, Interaction, RayState, Shots


def shoot(gen, mi_scene, src_positions, samples_per_src: int, max_depth: int, flags, seed: int,
          keep_state: bool = False) -> Shots:
    """Sionna's bounce loop, one wavefront per depth, without the targets.

    ``keep_state``: each depth's record also keeps what a ray needs to go on from there
    (:func:`~caviar_plugins.rt.shoot_cache.movers.by_way_of_movers`)."""
    shots, state = first_rays(gen, src_positions, samples_per_src, max_depth, flags, seed)
    shots.keeps_state = keep_state
    bounce(gen, mi_scene, shots, state, max_depth, flags, keep_state=keep_state)
    return shots


def enabled_interactions(flags, diffuse: bool = True) -> int:
    """Sionna's interaction-type flags of what ``flags`` (specular, diffuse, refraction,
    diffraction, edge diffraction) turn on; ``diffuse = False`` leaves diffuse reflection off."""
    InteractionType = adapter.ray_utilities()[0]
    specular_on, diffuse_on, refraction_on, diffraction_on, _ = flags
    enabled = 0
    for on, kind in ((specular_on, InteractionType.SPECULAR), (diffuse_on and diffuse, InteractionType.DIFFUSE),
                     (refraction_on, InteractionType.REFRACTION), (diffraction_on, InteractionType.DIFFRACTION)):
        if on:
            enabled |= int(kind)
    return enabled


def first_rays(gen, src_positions, samples_per_src: int, max_depth: int, flags, seed: int) -> tuple[Shots, RayState]:
    """The shots of :func:`shoot` before any bounce, and the rays' state as Sionna's loop
    starts it (its Fibonacci lattice from each source, its sampler seeded)."""
    dr, mi = jit()
    _, WedgeGeometry, fibonacci_lattice, _, spawn_ray_from_sources = adapter.ray_utilities()
    diffraction_on = flags[3]
    num_sources = dr.shape(src_positions)[1]
    n = samples_per_src * num_sources
    adapter.sampler(gen).seed(seed, n)
    ray = spawn_ray_from_sources(fibonacci_lattice, samples_per_src, src_positions)
    shots = Shots(width=n, samples=dr.zeros(adapter.sample_data_fields(), n * max(1, max_depth)),
                  src_indices=adapter.source_index_per_sample(num_sources, samples_per_src), k_tx=dr.copy(ray.d),
                  wedges=WedgeGeometry.build_with_size(n) if diffraction_on else None,
                  diffraction_depth=dr.zeros(mi.UInt, n))
    state = RayState(ray=ray, specular_chain=dr.full(mi.Bool, True, n),
                     hashes=[dr.zeros(mi.UInt64, n) for _ in adapter.hashers(gen)[0]],
                     active=dr.full(mi.Mask, True, n), loc_en_inter=dr.full(mi.UInt, enabled_interactions(flags), n))
    return shots, state


def interact(gen, mi_scene, sampler, ray, active, loc_en_inter, specular_chain, hashes, flags,
             waiting=None) -> Interaction:
    """One depth of Sionna's bounce loop without the targets, for the rays of ``ray``: the
    hit, the sampled interaction (Sionna's material and wedge sampling, its random numbers),
    the locally enabled interactions, the specular-chain flag and hashes updated, and the
    sample data of this depth. Rays in ``waiting`` (optional) keep their flag and hashes."""
    dr, mi = jit()
    InteractionType, _, _, hash_fnv1a, _ = adapter.ray_utilities()
    plane_hashers, edge_hashers = adapter.hashers(gen)
    _, _, _, diffraction_on, edge_diffraction_on = flags
    si = mi_scene.ray_intersect(ray, coherent=True, ray_flags=mi.RayFlags.Minimal, active=active)
    active = active & si.is_valid()
    sample1 = sampler.next_1d()
    sample2 = sampler.next_2d()
    sample2_diffraction = sampler.next_2d()
    s, normal, wedges = adapter.sample_radio_material(gen, si, ray.o, ray.d, sample1, sample2, sample2_diffraction,
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
    fields = adapter.sample_data_fields()(
        dr.select(active, int_type, 0), dr.select(active, dr.reinterpret_array(mi.UInt, si.shape), 0),
        dr.select(active, si.prim_index, 0), dr.select(active, si.p, mi.Point3f(0.0)), dr.select(active, s.pdf, 0.0))
    return Interaction(si=si, normal=normal, wedges=wedges, k_world=s.wo, active=active, loc_en_inter=loc_en_inter,
                       specular_chain=chain, hashes=new_hashes, diffuse=diffuse, diffraction=diffraction,
                       fields=fields)


def record(lane, index, p, n, diffuse, specular_chain, hashes, ahead: tuple | None = None) -> DepthRecord:
    """A depth's record of the rays ``lane`` (what the connect phase reads), gathered at
    ``index`` from arrays of hit points, normals, diffuse flags, chain flags and hashes;
    ``ahead``: (o, d, chain_next, loc) of the rays' next segments, already gathered."""
    dr, mi = jit()
    gathered = (dr.gather(mi.Point3f, p, index), dr.gather(mi.Normal3f, n, index), dr.gather(mi.Bool, diffuse, index),
                dr.gather(mi.Bool, specular_chain, index), [dr.gather(mi.UInt64, h, index) for h in hashes])
    dr.eval(lane, *gathered, *(ahead or ()))
    return DepthRecord.of(lane, *gathered, ahead=ahead)


def bounce(gen, mi_scene, shots: Shots, state: RayState, max_depth: int, flags, keep_state: bool) -> None:
    """The recorded bounces of the static scene (:func:`shoot`): Sionna's inner loop without
    the targets, one wavefront per depth, appending one record per depth to ``shots.depths``
    (the rays still alive there)."""
    dr, mi = jit()
    sampler = adapter.sampler(gen)
    diffraction_on = flags[3]
    n = shots.width
    ray, specular_chain, hashes = state.ray, state.specular_chain, state.hashes
    active, loc_en_inter = state.active, state.loc_en_inter
    lane = dr.arange(mi.UInt, n)
    for depth in range(1, max_depth + 1):
        x = interact(gen, mi_scene, sampler, ray, active, loc_en_inter, specular_chain, hashes, flags)
        si, normal, active, loc_en_inter = x.si, x.normal, x.active, x.loc_en_inter
        specular_chain, hashes, diffuse = x.specular_chain, x.hashes, x.diffuse
        dr.scatter(shots.samples, x.fields, dr.opaque(mi.UInt, (depth - 1) * n) + lane)
        if diffraction_on:
            shots.wedges = dr.select(x.diffraction, x.wedges, shots.wedges)
            shots.diffraction_depth = dr.select(x.diffraction, depth, shots.diffraction_depth)
        hit_p, chain_here = si.p, specular_chain
        ray = si.spawn_ray(d=x.k_world)
        specular_chain = specular_chain | diffuse
        sampler.schedule_state()
        # Everything of this depth in one kernel: a gather from an array not yet evaluated
        # would trace and run the intersection and the material sampling again for it.
        depth_state = [hit_p, normal, diffuse, chain_here, hashes, shots.samples, ray, specular_chain, active,
                       loc_en_inter, shots.wedges, shots.diffraction_depth]
        dr.eval(*[v for v in depth_state if v is not None])
        alive = dr.compress(active)
        ahead = None
        if keep_state:  # where each live ray goes next, and its state: for rays that now meet a moving object
            ahead = (dr.gather(mi.Point3f, ray.o, alive), dr.gather(mi.Vector3f, ray.d, alive),
                     dr.gather(mi.Bool, specular_chain, alive), dr.gather(mi.UInt, loc_en_inter, alive))
        shots.depths.append(record(alive, alive, hit_p, normal, diffuse, chain_here, hashes, ahead))
        if dr.width(alive) == 0:
            break


def bounce_in_one_loop(gen, mi_scene, shots: Shots, state: RayState, max_depth: int, flags, touch_shapes,
                       start) -> None:
    """:func:`bounce` (without ``keep_state``) as one Dr.Jit symbolic loop: its body is
    traced once per solve instead of once per depth (the tracing of Sionna's material and
    wedge sampling, not the rays, is what a few thousand rays cost), and each depth's
    record is written to flat buffers (depth-major) that are compressed afterwards. Each
    depth is :func:`interact`, as in :func:`bounce`; besides, a ray waits until its
    ``start`` depth, and with ``touch_shapes`` (:func:`~caviar_plugins.rt.scene.shape_table`)
    it is recorded only from its first hit on one of those shapes on (``state.touched``)."""
    dr, mi = jit()
    sampler = adapter.sampler(gen)
    n = shots.width
    width = dr.opaque(mi.UInt, n)
    lane = dr.arange(mi.UInt, n)
    size = n * max_depth
    out = {"recorded": dr.zeros(mi.Bool, size), "p": dr.zeros(mi.Point3f, size), "n": dr.zeros(mi.Normal3f, size),
           "diffuse": dr.zeros(mi.Bool, size), "specular_chain": dr.zeros(mi.Bool, size),
           "hashes": [dr.zeros(mi.UInt64, size) for _ in state.hashes]}
    with_wedges = shots.wedges is not None
    wedges_state = shots.wedges if with_wedges else mi.UInt(0)
    diffraction_depth = shots.diffraction_depth if with_wedges else mi.UInt(0)

    def cond(depth, *_):
        return depth <= max_depth

    def body(depth, ray, specular_chain, hashes, active, loc_en_inter, touched, wedges_kept, ddepth, sampler_):
        waiting = start > depth
        before = active
        x = interact(gen, mi_scene, sampler_, ray, active & ~waiting, loc_en_inter, specular_chain, hashes, flags,
                     waiting)
        si, normal, active, loc_en_inter = x.si, x.normal, x.active, x.loc_en_inter
        specular_chain, hashes, diffuse = x.specular_chain, x.hashes, x.diffuse
        at = (depth - 1) * width + lane
        dr.scatter(shots.samples, x.fields, at, ~waiting)
        if with_wedges:
            wedges_kept = dr.select(x.diffraction, x.wedges, wedges_kept)
            ddepth = dr.select(x.diffraction, depth, ddepth)
        if touch_shapes is not None:
            touched |= active & on_shapes(touch_shapes, si)
        recorded = active & touched
        dr.scatter(out["recorded"], recorded, at)
        for key, value in (("p", si.p), ("n", normal), ("diffuse", diffuse), ("specular_chain", specular_chain)):
            dr.scatter(out[key], value, at, recorded)
        for i, h in enumerate(hashes):
            dr.scatter(out["hashes"][i], h, at, recorded)
        ray = dr.select(waiting, ray, si.spawn_ray(d=x.k_world))
        specular_chain = specular_chain | diffuse
        active = dr.select(waiting, before, active)
        return (depth + 1, ray, specular_chain, hashes, active, loc_en_inter, touched, wedges_kept, ddepth,
                sampler_)

    loop_state = (dr.full(mi.UInt, 1, n), state.ray, state.specular_chain, list(state.hashes), state.active,
                  state.loc_en_inter, state.touched, wedges_state, diffraction_depth, sampler)
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
            shots.depths.append(DepthRecord.empty())
            continue
        alive = aligned_array(mi.UInt, rays.astype(np.uint32))
        shots.depths.append(record(alive, dr.opaque(mi.UInt, (depth - 1) * n) + alive, out["p"], out["n"],
                                   out["diffuse"], out["specular_chain"], out["hashes"]))
