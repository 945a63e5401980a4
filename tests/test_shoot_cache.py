"""The shoot cache (issue #18): solves served from recorded bounces find what Sionna's
own shoot-and-bounce loop finds, and the cache steps aside when the geometry changes."""

import numpy as np
import pytest

from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.radio import RadioConfig, RadioScene
from caviar_plugins.rt.scene import itu_material
from caviar_plugins.rt.settings import with_raytracing

# Diffuse reflection only adds paths where a material scatters: give concrete a
# scattering coefficient so that the diffuse branch (paths finalised in the loop) is
# exercised along with specular chains, refraction and diffraction.
SETTINGS = dict(samples_per_src=30_000, max_depth=4, threads=1, shoot_cache=True)  # ("auto" is off on CUDA)
ROUTE = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
RECEIVERS = {"a": ROUTE.at(0.0), "b": ROUTE.at(60.0), "c": ROUTE.at(150.0)}  # the SAR flight


def scene(shoot_cache: bool, scattering: float = 0.3, **kw) -> RadioScene:
    radio = RadioScene(with_raytracing(RadioConfig, **{**SETTINGS, "uav_mesh": False, "shoot_cache": shoot_cache,
                                                       **kw}), seed=5)
    radio.scene.radio_materials["itu_concrete"].scattering_coefficient = scattering
    return radio


def solve(radio: RadioScene, shift: float):
    radio.place({k: p + [shift, 0.0, 0.0] for k, p in RECEIVERS.items()})
    return radio.solve()


def assert_same_links(got, ref):
    for key in ref:
        x, y = got[key], ref[key]
        assert x.n_paths == y.n_paths, key
        assert x.los == y.los, key
        # The same paths, summed in another order (candidates land depth-major in the
        # buffer): equal to float32 noise.
        scale = np.abs(y.h).max()
        np.testing.assert_allclose(x.h, y.h, rtol=0, atol=2e-3 * scale, err_msg=key)
        assert abs(10 * np.log10(x.path_gain / y.path_gain)) < 0.01, key
        assert x.best_pair == y.best_pair, key


def test_cached_solves_find_the_paths_of_sionnas_loop():
    cached, plain = scene(True), scene(False)
    diffuse_paths = 0
    for shift in (0.0, 1.5, 3.0, 4.5):
        got, ref = solve(cached, shift), solve(plain, shift)
        assert_same_links(got, ref)
        diffuse_paths += sum(link.n_paths for link in ref.values())
    # The first solve of a geometry runs Sionna's loop, the second records the bounces,
    # every later one is served from them.
    assert cached.shoot_cache.shoots == 1 and cached.shoot_cache.connects == 3
    assert plain.shoot_cache is None
    assert diffuse_paths > 100


def test_without_scattering_the_cache_still_agrees():
    cached, plain = scene(True, scattering=0.0), scene(False, scattering=0.0)
    for shift in (0.0, 2.0, 4.0):
        assert_same_links(solve(cached, shift), solve(plain, shift))
    assert cached.shoot_cache.connects == 2


def test_a_changed_geometry_is_never_served_from_the_cache():
    cached = scene(True)
    for shift in (0.0, 1.0, 2.0):
        solve(cached, shift)
    assert cached.shoot_cache.connects == 2
    # A material changes: the next solve runs Sionna's loop on the new material.
    cached.scene.radio_materials["itu_concrete"].scattering_coefficient = 0.6
    fresh = scene(False, scattering=0.6)
    assert_same_links(solve(cached, 3.0), solve(fresh, 3.0))
    assert cached.shoot_cache.connects == 2
    # An object moves (the scene's 2 m cube, 3 m east): the same.
    cube = cached.scene.objects["Cube"]
    cube.position = np.asarray(cube.position, dtype=float).ravel() + [3.0, 0.0, 0.0]
    got = solve(cached, 3.0)
    assert cached.shoot_cache.connects == 2
    moved = scene(False, scattering=0.6)
    moved.scene.objects["Cube"].position = cube.position
    assert_same_links(got, solve(moved, 3.0))


def test_without_cache_moving_bodies_moving_uav_bodies_run_sionnas_loop_every_step():
    cached = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=True, cache_moving_bodies=False), seed=5)
    plain = RadioScene(with_raytracing(RadioConfig, **{**SETTINGS, "uav_mesh": True, "shoot_cache": False}), seed=5)
    for shift in (0.0, 2.5, 5.0):
        for radio in (cached, plain):
            radio.place({"u": RECEIVERS["a"] + [shift, 0.0, 0.0]})
        assert_same_links(cached.solve(), plain.solve())
    assert cached.shoot_cache.connects == 0 and cached.shoot_cache.shoots == 0


def keeps_sionnas_links(got, ref, where) -> tuple[int, int]:
    """Asserts that each cached link keeps what Sionna's loop found: the line-of-sight flag,
    at least its paths, its path gain or more (0.05 dB); returns how many links have more
    paths and how many the same best pair."""
    more = same_pair = 0
    for key in ref:
        x, y = got[key], ref[key]
        assert x.los == y.los, (where, key)
        assert x.n_paths >= y.n_paths, (where, key, x.n_paths, y.n_paths)
        assert 10 * np.log10(x.path_gain / y.path_gain) > -0.05, (where, key)
        more += x.n_paths > y.n_paths
        same_pair += x.best_pair == y.best_pair
    return more, same_pair


def test_moving_uav_bodies_are_served_from_the_cache_and_keep_sionnas_paths():
    """Bodies moving with two UAVs along the SAR route: every solve after the first two is
    served from the cache, and each link keeps what Sionna's loop (run every step, the body
    a new geometry) finds: the same line-of-sight flag, at least its paths, its path gain
    or more (the rays aimed at the bodies find body reflections Sionna's sparse rays miss:
    at 3e4 rays a 2 m body 200 m away is hit by about one ray)."""
    cached = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=True), seed=5)
    plain = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=True, cache_moving_bodies=False), seed=5)
    more, same_pair, links = 0, 0, 0
    times = (0.0, 30.0, 60.0, 90.0, 120.0)
    for t in times:
        pos = {"a": ROUTE.at(t), "b": ROUTE.at(t + 150.0)}
        cached.place(pos)
        plain.place(pos)
        more_here, same_here = keeps_sionnas_links(cached.solve(), plain.solve(), t)
        more, same_pair, links = more + more_here, same_pair + same_here, links + len(pos)
    assert cached.shoot_cache.connects == len(times) - 1 and cached.shoot_cache.shoots == 1
    assert plain.shoot_cache.connects == 0
    assert more >= 1 and same_pair >= links - 2, (more, same_pair, links)


def test_a_body_under_the_receiver_reflects_where_the_geometry_says():
    """Free space, one UAV: its 2 m metal body, 0.5 m under the antenna, reflects the
    transmitter's wave up to it. The cache (the body moving between solves) finds the line of
    sight and the reflection off the body's top at the delays of the straight line and of
    the image of the receiver in the top face, as Sionna's loop does with a million rays,
    at the same power."""
    tx = np.array([0.0, 0.0, 30.0])
    settings = dict(scene="empty", tx_position=tx.tolist(), tx_array=[1, 1], rx_array=[1, 1], pattern="iso",
                    max_depth=2, threads=1, uav_mesh=True, diffraction=False, shoot_cache=True)
    cached = RadioScene(with_raytracing(RadioConfig, **settings, samples_per_src=10_000), seed=2)
    dense = RadioScene(with_raytracing(RadioConfig, **{**settings, "samples_per_src": 1_000_000,
                                                       "shoot_cache": False}), seed=2)
    for x in (18.0, 19.0, 20.0):  # the body moves; the last solve is served from the cache
        uav = np.array([x, 0.0, 10.0])
        cached.place({"u": uav})
        got = cached.solve()["u"]
    assert cached.shoot_cache.connects == 2  # the first solve of a geometry is Sionna's
    dense.place({"u": uav})
    ref = dense.solve()["u"]
    rx = uav + [0.0, 0.0, 1.5]
    top = uav[2] + 1.0
    image = rx.copy()
    image[2] = 2 * top - rx[2]
    c = 299_792_458.0
    expected = sorted([np.linalg.norm(rx - tx) / c, np.linalg.norm(image - tx) / c])
    for radio in (cached, dense):
        valid = np.array(radio.last_paths.valid).ravel()
        tau = np.sort(np.array(radio.last_paths.tau).ravel()[valid])
        np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-12)
    assert abs(10 * np.log10(got.path_gain / ref.path_gain)) < 0.01


def test_the_bodies_are_put_back_bit_for_bit_after_the_bounces_are_recorded():
    radio = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=True), seed=5)
    body = None
    for shift in (0.0, 2.5):
        radio.place({"u": RECEIVERS["a"] + [shift, 0.0, 0.0]})
        body = radio.bodies["u"]
        before = np.array(body.mi_mesh.vertex_positions_buffer())
        radio.solve()  # the second solve records the bounces with the body out of the way
        assert np.array_equal(np.array(body.mi_mesh.vertex_positions_buffer()), before)
    assert radio.shoot_cache.shoots == 1 and body is not None


def test_path_buffer_overflow_is_reported_from_cached_solves():
    cached = scene(True, max_num_paths_per_src=5)
    with pytest.warns(RuntimeWarning, match="path buffer overflowed"):
        for shift in (0.0, 1.0, 2.0):
            links = solve(cached, shift)
    assert cached.shoot_cache.connects == 2
    assert links["a"].paths_dropped > 0


def test_chains_lost_to_sionnas_hash_table_are_found(monkeypatch):
    """Sionna drops a specular chain whose slot in its counter table another chain took.
    A table shrunk to 10,000 slots makes that happen at a small sample count: Sionna's loop
    then loses paths (and, not allowed a larger table, the tracer says so); the cache, which
    deduplicates exactly, finds those of the full table, and so does Sionna's loop once the
    tracer grows the table for a solve that found too many candidates for it."""
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    from caviar_plugins.rt import sionna_adapter

    full = scene(False)
    cached = scene(True, max_num_paths_per_src=10_000)
    for shift in (0.0, 1.0):
        solve(cached, shift)
    ref = solve(full, 2.0)
    assert full.tracer.chain_loss < sionna_adapter.CHAIN_LOSS and full.tracer.chain_slots == 0
    monkeypatch.setattr(SBCandidateGenerator, "MIN_SPEC_COUNT_SIZE", 10_000)
    monkeypatch.setattr(sionna_adapter, "MAX_CHAIN_SLOTS", 10_000)  # not allowed to grow: Sionna's loop as it is
    small = scene(False, max_num_paths_per_src=10_000)
    with pytest.warns(RuntimeWarning, match="lost to collisions in Sionna's table"):
        lossy = solve(small, 2.0)
    got = solve(cached, 2.0)
    assert cached.shoot_cache.connects == 2
    assert all(link.paths_dropped == 0 for link in (*got.values(), *lossy.values()))
    assert sum(link.n_paths for link in lossy.values()) < 0.97 * sum(link.n_paths for link in ref.values())
    assert small.tracer.chain_loss > 0.03
    assert_same_links(got, ref)
    monkeypatch.setattr(sionna_adapter, "MAX_CHAIN_SLOTS", 1 << 26)
    grown = scene(False, max_num_paths_per_src=10_000)
    found = solve(grown, 2.0)
    assert grown.tracer.chain_slots > 10_000 and grown.tracer.chain_loss <= sionna_adapter.CHAIN_LOSS
    for key, link in ref.items():  # a few tenths of a per cent lost at most, where over a tenth were
        assert ref[key].n_paths >= found[key].n_paths >= 0.995 * ref[key].n_paths, key
        assert abs(10 * np.log10(found[key].path_gain / link.path_gain)) < 0.05, key
    resumed = scene(False, max_num_paths_per_src=10_000)  # (a checkpoint keeps the grown table)
    resumed.restore(grown.snapshot())
    assert resumed.tracer.chain_slots == grown.tracer.chain_slots


def test_moving_vehicles_are_served_from_the_cache_and_keep_sionnas_paths():
    """Cars (pool boxes, as sionna-traffic-link moves them) driving under the SAR flight:
    declared moving objects, they leave the recorded bounces alone, so every solve after the
    first two is served from the cache, and each link keeps what Sionna's loop (run every
    step, the cars a new geometry) finds: the line-of-sight flag, at least its paths, its
    path gain or more, the best pair; a parked box gets no rays."""
    from caviar_plugins.rt.scatterers import Body, ScattererPool

    def with_pool(**kw):
        radio = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=False, rays_per_moving_object=512,
                                           **kw), seed=5)
        metal = itu_material("car-metal", "metal", thickness=0.01)
        pool = ScattererPool(radio.scene, {"vehicle": 4}, {"vehicle": metal}, prefix="cars")
        radio.add_moving_objects(pool.objects(), away=pool.parked, boxes=pool.boxes)
        return radio, pool

    cached, cached_pool = with_pool()
    plain, plain_pool = with_pool(cache_moving_bodies=False)
    same_pair, links = 0, 0
    for k in range(5):
        pos = {"a": ROUTE.at(10.0 * k), "b": ROUTE.at(150.0 + 10.0 * k)}
        cars = [Body(f"car{i}", "vehicle", (*(p[:2] + [6.0 * i - 3.0 + 2.0 * k, 4.0]), 0.0), 0.1, (4.5, 1.8, 1.5))
                for i, p in enumerate(pos.values())]
        for radio, pool in ((cached, cached_pool), (plain, plain_pool)):
            pool.update(cars)
            radio.place(pos)
        _, same_here = keeps_sionnas_links(cached.solve(force=True), plain.solve(force=True), k)
        same_pair, links = same_pair + same_here, links + len(pos)
    assert cached.shoot_cache.connects == 4 and cached.shoot_cache.shoots == 1
    assert plain.shoot_cache.connects == 0
    assert same_pair >= links - 1, (same_pair, links)
    (mesh,) = cached_pool.objects()  # the four boxes, one mesh: two show cars, two are parked
    assert len(cached.movers.boxes_of(mesh)) == 2 and cached.movers.rays_at(mesh) == 512  # 512 at each car
    cached_pool.update([])
    assert cached_pool.parked(mesh) and cached.movers.rays_at(mesh) == 0 and len(cached.movers.boxes_of(mesh)) == 0


def test_the_box_prefilter_finds_every_recorded_ray_that_now_meets_a_moving_object_first():
    """Each solve casts again, in the whole scene, only the recorded rays that meet a moving
    object's bounding box (a scene of boxes): the rays it finds on a moving object are
    exactly those that intersecting every recorded ray with the whole scene (the surface
    interaction, as before the prefilter) finds there first."""
    import mitsuba as mi

    from caviar_plugins.rt.scatterers import Body, ScattererPool
    from caviar_plugins.rt.scene import on_shapes, shape_table
    from caviar_plugins.rt.shoot_cache.movers import boxes_scene, met_by_movers

    radio = RadioScene(with_raytracing(RadioConfig, **SETTINGS, uav_mesh=True, rays_per_moving_object=64), seed=5)
    metal = itu_material("car-metal", "metal", thickness=0.01)
    pool = ScattererPool(radio.scene, {"vehicle": 3}, {"vehicle": metal}, prefix="cars")
    radio.add_moving_objects(pool.objects(), away=pool.parked, boxes=pool.boxes)
    for k in range(2):  # the second solve records the bounces (with where each ray goes next)
        pos = {"a": ROUTE.at(10.0 * k), "b": ROUTE.at(150.0 + 10.0 * k)}
        pool.update([Body(f"bus-{key}", "vehicle", (*(p[:2] + [3.0 + k, 2.0]), 0.0), 0.3, (12.0, 2.5, 4.0))
                     for key, p in pos.items()])
        radio.place(pos)
        radio.solve(force=True)
    shots = radio.shoot_cache.shots
    moving = radio.moving_objects()
    present = [o for o in moving if radio.movers.rays_at(o) != 0]
    boxes = np.concatenate([radio.movers.boxes_of(o) for o in present])
    assert len(boxes) == 4  # two buses, two UAV bodies (the third bus's box is parked)
    table = shape_table(radio.scene, moving)
    max_depth = SETTINGS["max_depth"]
    mi_scene = radio.scene.mi_scene
    got = {d: pick.tolist() for d, pick in met_by_movers(mi_scene, shots, max_depth, table, boxes_scene(boxes))}
    every = {}
    for d, rec in enumerate(shots.depths[: max_depth - 1], start=1):
        assert rec.size > 1000  # (most rays are not near any moving object)
        si = mi_scene.ray_intersect(mi.Ray3f(rec.o, rec.d))
        on = np.flatnonzero(np.asarray(on_shapes(table, si), dtype=bool))
        if len(on):
            every[d] = on.tolist()
    assert got == every and sum(map(len, every.values())) >= 5, every


def test_the_one_loop_bounce_records_what_the_per_depth_bounce_records():
    """The moving objects' rays bounce in one Dr.Jit symbolic loop (``bounce_in_one_loop``),
    the recorded static bounces one wavefront per depth (``bounce``). From the same first
    rays (Sionna's lattice, its sampler seeded alike) both keep the same rays alive at each
    depth, with the same chain groups, diffuse rays, hashes and diffracting depths, hit points,
    normals and sample data, bit for bit (threads = 1)."""
    import drjit as dr
    import mitsuba as mi

    from caviar_plugins.rt.shoot_cache.shoot import bounce, bounce_in_one_loop, first_rays

    radio = scene(True, samples_per_src=4000, max_depth=3)
    c = radio.cfg.raytracing
    gen = radio.shoot_cache.generator  # (Sionna's own generator, which the cache stands in for)
    source = radio.scene.sources(True, False)[0]
    flags = (c.specular_reflection, c.diffuse_reflection, c.refraction, c.diffraction, False)
    mi_scene = radio.scene.mi_scene
    per_depth, state = first_rays(gen, source, c.samples_per_src, c.max_depth, flags, radio.seed)
    bounce(gen, mi_scene, per_depth, state, c.max_depth, flags, keep_state=False)
    one, state = first_rays(gen, source, c.samples_per_src, c.max_depth, flags, radio.seed)
    state.touched = dr.full(mi.Bool, True, one.width)
    bounce_in_one_loop(gen, mi_scene, one, state, c.max_depth, flags, None, start=dr.full(mi.UInt, 1, one.width))
    assert len(per_depth.depths) == len(one.depths) == c.max_depth
    for a, b in zip(per_depth.depths, one.depths, strict=True):
        assert len(np.asarray(a.lane)) > 100 and np.array_equal(np.asarray(a.lane), np.asarray(b.lane))
        for key in ("lanes", "grouped", "starts", "sizes", "diffuse_rays", "h0", "h1"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
        assert np.array_equal(np.array(a.p), np.array(b.p)) and np.array_equal(np.array(a.n), np.array(b.n))
    assert len(per_depth.depths[0].diffuse_rays) > 0 and len(per_depth.depths[0].grouped) > 0
    for field in ("interaction_type", "shape", "primitive", "vertex", "prob"):
        assert np.array_equal(np.array(getattr(per_depth.samples, field)), np.array(getattr(one.samples, field))), field
    assert np.array_equal(np.asarray(per_depth.diffraction_depth), np.asarray(one.diffraction_depth))


def test_a_negative_ray_count_for_moving_objects_is_refused_by_name():
    with pytest.raises(ValueError, match=r"rays_per_moving_object: expected >= 0 .*got -1"):
        with_raytracing(RadioConfig, rays_per_moving_object=-1)


def test_sionnas_own_first_rays_that_meet_a_moving_body_are_those_a_slab_test_finds():
    """With ``rays_per_moving_object = 0`` no rays are aimed: the rays of Sionna's own
    Fibonacci lattice from the transmitter whose first hit is now a moving body go on from
    it. In free space the ones found are those that an independent ray-box (slab) test in
    float64 finds on the body's box, up to a centimetre at its edges; and the solve finds the
    reflection off the body's top that Sionna's loop finds."""
    from caviar_plugins.rt.scene import shape_table
    from caviar_plugins.rt.shoot_cache.movers import boxes_scene, first_rays_met

    tx = np.array([0.0, 0.0, 30.0])
    settings = dict(scene="empty", tx_position=tx.tolist(), tx_array=[1, 1], rx_array=[1, 1], pattern="iso",
                    max_depth=2, threads=1, uav_mesh=True, diffraction=False, rays_per_moving_object=0,
                    shoot_cache=True)
    radio = RadioScene(with_raytracing(RadioConfig, **settings, samples_per_src=100_000), seed=2)
    for x in (18.0, 20.0):  # the second solve records the bounces
        uav = np.array([x, 0.0, 10.0])
        radio.place({"u": uav})
        got = radio.solve()["u"]
    assert radio.shoot_cache.connects == 1
    body = radio.bodies["u"]
    lo, hi = np.array(body.mi_mesh.bbox().min, dtype=float), np.array(body.mi_mesh.bbox().max, dtype=float)
    shots = radio.shoot_cache.shots
    found = first_rays_met(radio.scene.mi_scene, shots, tx, shape_table(radio.scene, [body]),
                           boxes_scene(np.array([[lo, hi]])))
    lattice = np.array(shots.k_tx, dtype=float).reshape(3, -1).T

    def slab(d, lo, hi):
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (lo - tx) / d, (hi - tx) / d
        near, far = np.nanmax(np.minimum(t0, t1), axis=1), np.nanmin(np.maximum(t0, t1), axis=1)
        return (far >= near) & (far > 0)

    inner = lattice[slab(lattice, lo + 0.01, hi - 0.01)]
    assert len(inner) >= 50
    assert slab(found, lo - 0.01, hi + 0.01).all()  # nothing off the box
    assert len(found) >= len(inner)  # and every ray well inside it
    assert {tuple(np.round(d, 6)) for d in inner} <= {tuple(np.round(d, 6)) for d in found}
    plain = RadioScene(with_raytracing(RadioConfig, **settings, samples_per_src=100_000, cache_moving_bodies=False),
                       seed=2)
    plain.place({"u": uav})
    ref = plain.solve()["u"]
    assert got.n_paths == ref.n_paths == 2  # the line of sight and the top's reflection
    assert abs(10 * np.log10(got.path_gain / ref.path_gain)) < 0.01


def test_targets_behind_a_reflecting_plane_go_untested_and_the_paths_stay(monkeypatch):
    """A specular chain whose last interaction is a reflection cannot reach a target on the
    far side of that plane, so the cache does not test the target's visibility there. The
    links are those found with every pair tested, and about half the tests are gone."""
    from caviar_plugins.rt.shoot_cache import connect

    tested = []
    visibility = connect.visibility

    def counting(mi_scene, rec, tgt, rays, targets):
        tested.append(len(rays))
        return visibility(mi_scene, rec, tgt, rays, targets)

    monkeypatch.setattr(connect, "visibility", counting)
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=1_000_000, uav_mesh=False, threads=1,
                                       shoot_cache=True), seed=0)
    # 30 receivers along the SAR route, as look-ahead places 10 UAVs: there, a path that
    # diffracts and then reflects on a face of the diffracting edge is lost if the side is
    # taken from the recorded ray (the first version of the cull lost one at u3, 0.5 m on).
    along = {f"u{i}": ROUTE.at(s) for i, s in enumerate(np.linspace(0.0, 0.95 * ROUTE.length, 30))}
    radio.place(along)
    for _ in range(2):  # Sionna's loop, then the recording
        radio.solve(force=True)
    # Sionna's loop lost over 1 % of the 30 receivers' chains to its table's collisions, so the
    # tracer solved again: the cache served that solve (recording), and the next connects
    assert radio.tracer.chain_slots > 0
    counts = {}
    for shift in (0.5,):
        links = {}
        for cull in (False, True):
            radio.shoot_cache.cull_behind = cull
            tested.clear()
            radio.place({f"u{i}": ROUTE.at(s + shift) for i, s in enumerate(
                np.linspace(0.0, 0.95 * ROUTE.length, 30))})
            links[cull] = radio.solve(force=True)
            counts.setdefault(cull, []).append(sum(tested))
        assert_same_links(links[True], links[False])
        for key, link in links[True].items():
            assert link.n_paths == links[False][key].n_paths > 0, key
    assert radio.shoot_cache.connects == 4  # the recording solve connects too
    saved = 1 - sum(counts[True]) / sum(counts[False])
    assert 0.2 < saved < 0.9, counts


def _diffuse_paths_through(p, lo, hi) -> tuple[int, int]:
    """(diffuse paths with a segment before the last that crosses the box [lo, hi], diffuse
    paths) of one receiver's PathData: a slab test on the segments from the transmitter
    through the path's interaction points."""
    from caviar_plugins.radio.path_data import DIFFUSE

    crossing = total = 0
    for i in range(p.n_paths):
        depth = int((p.interactions[:, i] > 0).sum())
        if depth == 0 or p.interactions[depth - 1, i] != DIFFUSE:
            continue
        total += 1
        points = np.r_[p.tx_position[None], p.vertices[:depth, i]]
        for a, b in zip(points[:-1], points[1:], strict=True):
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (lo - a) / (b - a), (hi - a) / (b - a)
            enter, leave = np.nanmax(np.minimum(t1, t2)), np.nanmin(np.maximum(t1, t2))
            if leave >= max(enter, 1e-6) and enter <= 1 - 1e-6:
                crossing += 1
                break
    return crossing, total


def test_a_diffuse_path_whose_earlier_segment_meets_a_moving_object_is_dropped():
    """A diffuse path is not refined by the image method, so the cache checks its earlier
    segments against the moving objects itself. A 30 m slab (a pool box) 23 m under the
    transmitter: without it about 26 diffuse paths per receiver pass where it will be; with
    it, neither the cache nor Sionna's loop keeps any path through it (a slab test on each
    path's segments), and the cache's diffuse paths number Sionna's within 5 %."""
    from caviar_plugins.rt.scatterers import Body, ScattererPool

    def with_pool(**kw):
        radio = scene(True, uav_mesh=False, rays_per_moving_object=512, **kw)
        metal = itu_material("slab-metal", "metal", thickness=0.01)
        pool = ScattererPool(radio.scene, {"vehicle": 1}, {"vehicle": metal}, prefix="slab")
        radio.add_moving_objects(pool.objects(), away=pool.parked, boxes=pool.boxes)
        radio.keep_paths = True
        return radio, pool

    size = (30.0, 30.0, 2.0)
    cached, cached_pool = with_pool()
    plain, plain_pool = with_pool(cache_moving_bodies=False)
    for k in range(3):
        pos = {"a": ROUTE.at(10.0 * k), "b": ROUTE.at(150.0 + 10.0 * k)}
        centre = np.array([-154.0 + k, 64.0, 95.0])  # (moved each step: Sionna's loop traces it anew)
        # (1 mm inside the slab: a path's vertex on its surface, in float32, is not a crossing)
        lo, hi = centre - [15.0, 15.0, 0.0] + 1e-3, centre + [15.0, 15.0, 2.0] - 1e-3
        for radio, pool in ((cached, cached_pool), (plain, plain_pool)):
            pool.update([Body("slab", "vehicle", tuple(centre), 0.0, size)] if k else [])
            radio.place(pos)
        got, ref = cached.solve(force=True), plain.solve(force=True)
        for key in pos:
            (cross_got, diffuse_got), (cross_ref, diffuse_ref) = (
                _diffuse_paths_through(links[key].paths, lo, hi) for links in (got, ref))
            if k == 0:  # no slab yet (Sionna's loop in both): paths pass where it will be
                assert cross_got == cross_ref >= 10, (key, cross_got, cross_ref)
            else:
                assert cross_got == 0 and cross_ref == 0, (k, key, cross_got, cross_ref)
                assert abs(diffuse_got - diffuse_ref) <= 0.05 * diffuse_ref, (k, key, diffuse_got, diffuse_ref)
    assert cached.shoot_cache.connects == 2 and plain.shoot_cache.connects == 0


def test_the_default_turns_the_cache_on_for_the_cpu_and_off_on_cuda():
    """``shoot_cache = "auto"`` (the default) chooses by Dr.Jit backend from measurements: on
    for LLVM, where a cached solve is a fraction of Sionna's loop; off on CUDA, where it
    measured slower (docs/tutorials/gpu-machine.md). A bad value is refused by its key."""
    from caviar_plugins.network.raytraced import NETWORK_RAYS
    from caviar_plugins.rt.solver import use_shoot_cache

    assert RadioConfig().raytracing.shoot_cache == "auto" and NETWORK_RAYS.shoot_cache == "auto"
    assert use_shoot_cache("auto", "llvm_ad_mono_polarized") and use_shoot_cache("auto", "llvm_ad_rgb")
    assert not use_shoot_cache("auto", "cuda_ad_mono_polarized") and not use_shoot_cache("auto", "cuda_ad_rgb")
    assert use_shoot_cache(True, "cuda_ad_mono_polarized") and not use_shoot_cache(False, "llvm_ad_rgb")
    import mitsuba as mi

    on_cpu = not str(mi.variant()).startswith("cuda")
    assert use_shoot_cache("auto") is on_cpu
    default = RadioScene(with_raytracing(RadioConfig, scene="empty", samples_per_src=100, uav_mesh=False))
    assert (default.shoot_cache is not None) is on_cpu
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match=r'shoot_cache: expected true, false or "auto"'):
            with_raytracing(RadioConfig, shoot_cache=bad)
