"""SUMO traffic in the loop (real SUMO through libsumo) and moving scatterers in the
ray-traced scene (real Sionna RT, small sample counts), checked against independent
computations."""

import math
import pathlib
import subprocess

import numpy as np
import pytest

import caviar
from caviar.plugin import Context, Inbox, Message
from caviar_plugins.schema import LINK, POSITIONS, position_payload
from caviar_plugins.traffic.sumo import binary
from configs import episode, module
from conftest import write_config

FC = 40e9
LAMBDA = 299_792_458.0 / FC


@pytest.fixture(scope="module")
def grid(tmp_path_factory) -> pathlib.Path:
    """A 3 x 3 grid of 150 m streets with sidewalks and crossings (SUMO's netgenerate)."""
    d = tmp_path_factory.mktemp("grid")
    net = d / "grid.net.xml"
    subprocess.run([binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "150",
                    "--sidewalks.guess", "true", "--crossings.guess", "true", "-o", str(net)],
                   check=True, capture_output=True)
    return net


DEMAND = "vehicles = { passenger = 5, bus = 1 }\npedestrians = 3"


def traffic_config(tmp_path, net, seed=3, steps=6, ts=0.5, demand=DEMAND):
    params = f'net = "{net}"\n{demand}\nwindow_s = 2.0\nmin_trip_m = 100.0\nsubsteps = 2\n'
    text = episode(ts, ["mobility"], steps=steps, seed=seed) + module("traffic", "mobility", "sumo-traffic", params,
                                                                       params_table=True)
    return write_config(tmp_path, text, f"traffic-{seed}.toml")


def positions(log):
    p = log.topic(POSITIONS)
    return [(r["time"], r["UE_Id"], r["position"]["x"], r["position"]["y"]) for r in p.iter_rows(named=True)]


def test_lockstep_and_same_seed_same_positions(tmp_path, grid):
    logs = {}
    for name, seed, extra in (("a", 3, ""), ("b", 3, ""), ("c", 4, ""), ("traci", 3, 'backend = "traci"')):
        cfg = traffic_config(tmp_path, grid, seed=seed, steps=40, ts=1.0, demand=DEMAND + "\n" + extra)
        logs[name] = caviar.Simulation.from_toml(cfg, out=tmp_path / name).run()
    log = logs["a"]
    traffic = log.topic("3D.mobility.traffic")
    # SUMO's own clock equals the engine's at every step (Ts = 1 s in 2 SUMO substeps).
    assert traffic["sumo_time"].to_list() == traffic["time"].to_list() == [float(k) for k in range(40)]
    pos = log.topic(POSITIONS)
    assert set(pos["UE_type"]) == {"car", "bus", "pedestrian"}
    assert pos.filter(pos["UE_type"] == "bus")["dimensions"].to_list()[0] == {"length": 12.0, "width": 2.5,
                                                                              "height": 3.4}
    # Every UE seen was announced as departed, once, no later than its first position.
    departed = log.topic("3D.mobility.departed")
    assert sorted(departed["UE_Id"]) == sorted(set(pos["UE_Id"])) and departed["UE_Id"].is_unique().all()
    first_seen = {r["UE_Id"]: r["time"] for r in reversed(list(pos.iter_rows(named=True)))}
    assert all(r["time"] <= first_seen[r["UE_Id"]] for r in departed.iter_rows(named=True))
    # Counts per step add up.
    n = pos.group_by("time").len().sort("time")
    assert dict(zip(n["time"], n["len"], strict=True)) == {r["time"]: r["vehicles"] + r["persons"]
                                              for r in traffic.iter_rows(named=True) if r["vehicles"] + r["persons"]}
    # Arrivals are announced once, after which the UE is gone.
    arrived = log.topic("3D.mobility.arrived")
    assert arrived.height >= 1 and set(arrived["UE_Id"]) <= set(departed["UE_Id"])
    for r in arrived.iter_rows(named=True):
        assert pos.filter((pos["UE_Id"] == r["UE_Id"]) & (pos["time"] >= r["time"])).height == 0
    assert positions(logs["a"]) == positions(logs["b"]) == positions(logs["traci"])
    assert positions(logs["a"]) != positions(logs["c"])


def test_bad_input_is_a_clear_error_naming_the_file(tmp_path, grid, cli):
    # A network that does not exist: found by validate, before a run directory exists.
    cfg = traffic_config(tmp_path, tmp_path / "missing.net.xml")
    with pytest.raises(caviar.ConfigError, match=r"modules\.traffic\.params\.net: .*missing\.net\.xml: no such SUMO"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "r1")
    assert not (tmp_path / "r1").exists()
    # A route file on edges the network does not have.
    routes = tmp_path / "other.rou.xml"
    routes.write_text('<routes><vehicle id="v0" depart="0"><route edges="nowhere elsewhere"/></vehicle></routes>')
    cfg = traffic_config(tmp_path, grid, demand=f'routes = ["{routes}"]')
    with pytest.raises(caviar.RunError, match=r"SUMO cannot load .*other\.rou\.xml.*nowhere"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "r2").run()
    # On the command line that is bad input, not a crash: exit 2, the file named, no traceback.
    p = cli("run", cfg, "--out", tmp_path / "r2-cli")
    assert p.returncode == 2 and "other.rou.xml" in p.stderr and "Traceback" not in p.stderr, p.stderr
    # A vehicle type the route file does not define.
    routes.write_text('<routes><vehicle id="v0" depart="0" type="spaceship"><route edges="A0B0 B0C0"/></vehicle>'
                      '</routes>')
    with pytest.raises(caviar.RunError, match=r"other\.rou\.xml.*spaceship"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "r3").run()
    # A vehicle class SUMO does not know: a parameter error (exit 2, file and line).
    cfg = traffic_config(tmp_path, grid, demand="vehicles = { spaceship = 1 }")
    p = cli("run", cfg)
    assert p.returncode == 2 and "modules.traffic.params" in p.stderr and "unknown vehicle class 'spaceship'" \
        in p.stderr and str(cfg.name) in p.stderr, p.stderr


# -- the radio side -------------------------------------------------------------


def test_the_pool_moves_boxes_without_scene_edits_and_reuses_them(tmp_path):
    from caviar_plugins.rt.scatterers import Body, PoolFull, ScattererPool, box_vertices

    plugin = radio_plugin(tmp_path, vehicle_pool=2, person_pool=1)
    pool, scene = plugin.pool, plugin.radio.scene
    edits = []
    scene_edit = scene.edit
    scene.edit = lambda *a, **kw: (edits.append(1), scene_edit(*a, **kw))
    car = Body("car", "vehicle", (10.0, 5.0, 0.0), 0.4, (4.5, 1.8, 1.5), (3.0, 1.0, 0.0))
    bus = Body("bus", "vehicle", (-20.0, 0.0, 0.0), 1.2, (12.0, 2.5, 3.4))
    assert pool.update([car, bus]) == 2 and pool.used == {"car": ("vehicle", 0), "bus": ("vehicle", 1)}
    np.testing.assert_allclose(pool.vertices_of("bus"), box_vertices(bus.center, bus.yaw, bus.size), atol=1e-4)
    np.testing.assert_allclose(pool.velocity_of("car"), [3.0, 1.0, 0.0])
    # One mesh per group (one shape in the solver's virtual calls), a box per 12 triangles.
    assert [o.name for o in pool.objects()] == ["traffic-vehicle-boxes", "traffic-person-boxes"]
    assert pool.key_at(pool.meshes["vehicle"].object_id, 12 + 5) == "bus"
    assert pool.key_at(pool.meshes["vehicle"].object_id, 5) == "car"
    assert pool.key_at(pool.meshes["person"].object_id, 5) is None  # parked
    assert pool.update([car, bus]) == 0  # nothing moved: nothing rewritten
    van = Body("van", "vehicle", (0.0, 30.0, 0.0), 0.0, (5.0, 2.0, 2.2))
    pool.update([car, van])  # the bus left, a van came: it takes the bus's box
    assert pool.used["van"] == ("vehicle", 1) and edits == []
    with pytest.raises(PoolFull):
        pool.update([car, van, bus])
    ScattererPool.update(pool, [car, van, bus], grow=True)
    assert pool.capacity["vehicle"] == 4 and len(edits) == 1
    # The grown mesh replaced the old one and shows the same boxes.
    assert [o.name for o in pool.objects()] == ["traffic-vehicle-boxes-1", "traffic-person-boxes"]
    assert "traffic-vehicle-boxes" not in scene.objects
    np.testing.assert_allclose(pool.vertices_of("car"), box_vertices(car.center, car.yaw, car.size), atol=1e-4)
    np.testing.assert_allclose(pool.vertices_of("bus"), box_vertices(bus.center, bus.yaw, bus.size), atol=1e-4)
    assert pool.velocity_of("car").tolist() == [3.0, 1.0, 0.0]


def test_the_uav_and_traffic_pools_move_in_one_scene_update(tmp_path):
    """Both pools' boxes are written, then the scene is updated once (one acceleration-
    structure rebuild per step, not one per pool); unmoved boxes update nothing."""
    from caviar_plugins.rt.scatterers import Body, box_vertices, update_pools

    plugin = radio_plugin(tmp_path, vehicle_pool=2, person_pool=1)
    plugin._new_uav_pool({"uav": 1})
    scene = plugin.radio.scene
    params = scene.mi_scene_params
    updates = []
    update = params.update
    params.update = lambda *a, **kw: (updates.append(1), update(*a, **kw))[1]
    uav = Body("uav1", "uav", (0.0, 0.0, 20.0), 0.0, (2.0, 2.0, 2.0), (5.0, 0.0, 0.0))
    car = Body("car", "vehicle", (10.0, 5.0, 0.0), 0.4, (4.5, 1.8, 1.5), (3.0, 1.0, 0.0))
    assert update_pools([(plugin.uav_pool, [uav]), (plugin.pool, [car])]) == [1, 1] and updates == [1]
    for pool, body in ((plugin.uav_pool, uav), (plugin.pool, car)):
        np.testing.assert_allclose(pool.vertices_of(body.key), box_vertices(body.center, body.yaw, body.size),
                                   atol=1e-4)
        np.testing.assert_allclose(pool.velocity_of(body.key), body.velocity)
    assert update_pools([(plugin.uav_pool, [uav]), (plugin.pool, [car])]) == [0, 0] and updates == [1]
    other = radio_plugin(tmp_path)
    with pytest.raises(ValueError, match="different scenes"):
        update_pools([(plugin.pool, [car]), (other.pool, [])])


def radio_plugin(tmp_path, **kw):
    from caviar_plugins.rt.settings import with_raytracing
    from caviar_plugins.traffic.link import SionnaTrafficLink, SionnaTrafficLinkParams

    params = dict(scene="empty", samples_per_src=2000, max_depth=1, tx_array=[1, 1], rx_array=[1, 1],
                  pattern="iso", uav_mesh=False, antenna_offset=[0.0, 0.0, 0.0], tx_orientation=[0.0, 0.0, 0.0],
                  frequency_hz=FC, vehicle_pool=4, person_pool=2, publish_channels=False)
    params.update(kw)
    plugin = SionnaTrafficLink()
    plugin.setup(Context(name="comm", params=with_raytracing(SionnaTrafficLinkParams, **params), seed=1, ts=1.0,
                         steps=None, every=1, offset=0, run_dir=tmp_path, config_dir=tmp_path))
    return plugin


def step(plugin, t, payloads):
    msgs = [Message(POSITIONS, p) for p in payloads]
    return {m[1]["UE_Id"]: m[1] for m in plugin.step(t, Inbox(msgs)) if m[0] == LINK}


def test_a_vehicle_stopped_on_the_line_lowers_the_path_gain(tmp_path, grid):
    # A car from SUMO, stopped 60 m along edge A0B0 (x from 0 to 150 m at y = 0).
    routes = tmp_path / "stop.rou.xml"
    routes.write_text('<routes><vehicle id="blocker" depart="0"><route edges="A0B0 B0C0"/>'
                      '<stop lane="A0B0_1" endPos="65" duration="1000"/></vehicle></routes>')
    cfg = traffic_config(tmp_path, grid, steps=30, ts=1.0, demand=f'routes = ["{routes}"]')
    log = caviar.Simulation.from_toml(cfg, out=tmp_path / "stop").run()
    car = log.topic(POSITIONS).filter(caviar.load_run(tmp_path / "stop").topic(POSITIONS)["UE_Id"] == "blocker")
    last = car.row(-1, named=True)
    assert last["speed"] == 0.0 and last["UE_type"] == "car"
    car_msg = {k: last[k] for k in ("UE_type", "UE_Id", "position", "heading", "speed", "velocity", "dimensions")}
    c = np.array([last["position"]["x"], last["position"]["y"]])
    heading = np.array([math.cos(last["heading"]), math.sin(last["heading"])])
    normal = np.array([-heading[1], heading[0]])
    tx = np.append(c - 15 * normal, 1.0)
    rx = np.append(c + 15 * normal, 1.0)  # the car (1.5 m high) stands across the Tx-Rx line at 1 m
    plugin = radio_plugin(tmp_path, tx_position=tx.tolist(), max_depth=3, samples_per_src=20000)
    ue = position_payload("ue", rx, "pedestrian-phone")
    with_car = step(plugin, 29.0, [car_msg, ue])["ue"]
    without = step(plugin, 29.0, [ue])["ue"]
    print("path gain without/with the car:", without["path_gain_db"], with_car["path_gain_db"], with_car["n_paths"])
    assert without["los"] and without["blocker"] is None
    assert not with_car["los"] and with_car["blocker"] == "blocker"
    assert without["path_gain_db"] - with_car["path_gain_db"] >= 10.0
    free_space = 20 * math.log10(LAMBDA / (4 * math.pi * 30.0))
    assert without["path_gain_db"] == pytest.approx(free_space, abs=0.1)


def test_a_moving_car_reflects_where_the_image_method_says_on_the_shoot_cache(tmp_path):
    """Free space, a metal car driving past a line of sight: its side reflects the wave. With
    the car a moving object of the shoot cache, the solves after the first two are served
    from it, and the last finds the line of sight and the reflection off the car's side at
    the delays of the straight line and of the receiver's image in the side's plane (an
    independent computation), at the power Sionna's loop finds with a million rays."""
    tx, rx = np.array([0.0, 0.0, 1.0]), np.array([40.0, 0.0, 1.0])
    plugin = radio_plugin(tmp_path, tx_position=tx.tolist(), max_depth=2, samples_per_src=10_000,
                          diffraction=False, threads=1, shoot_cache=True)  # ("auto" is off on CUDA)
    ue = position_payload("ue", rx, "pedestrian-phone")
    for x in (17.0, 18.5, 20.0):  # the car's footprint centre, 5 m off the line, heading +x
        car = position_payload("car", (x, 5.0, 0.0), "car")
        car.update(heading=0.0, speed=10.0, velocity={"x": 10.0, "y": 0.0, "z": 0.0},
                   dimensions={"length": 4.5, "width": 1.8, "height": 1.5})
        link = step(plugin, x, [car, ue])["ue"]
    radio = plugin.radio
    assert radio.shoot_cache.shoots == 1 and radio.shoot_cache.connects == 2
    side = 5.0 - 1.8 / 2  # the car's side facing the line, the plane y = 4.1
    image = rx * [1.0, 1.0, 1.0] + [0.0, 2 * side, 0.0]
    c = 299_792_458.0
    expected = sorted([np.linalg.norm(rx - tx) / c, np.linalg.norm(image - tx) / c])
    valid = np.array(radio.last_paths.valid).ravel()
    tau = np.sort(np.array(radio.last_paths.tau).ravel()[valid])
    np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-12)
    c_ = radio.cfg.raytracing
    from caviar_plugins.rt.scene import sionna_rt

    dense = sionna_rt().PathSolver()(radio.scene, max_depth=2, samples_per_src=1_000_000, synthetic_array=True,
                                     los=True, specular_reflection=True, diffuse_reflection=c_.diffuse_reflection,
                                     refraction=c_.refraction, diffraction=False, seed=radio.seed)
    h = dense.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")
    dense_db = 10 * np.log10(np.mean(np.abs(h) ** 2))
    assert link["path_gain_db"] == pytest.approx(dense_db, abs=0.01)
    free_space = 20 * math.log10(LAMBDA / (4 * math.pi * 40.0))
    assert abs(link["path_gain_db"] - free_space) > 0.1  # the reflection counts


def test_a_moving_box_shifts_the_doppler_of_its_reflection_as_the_geometry_and_sionna_say(tmp_path):
    """Two cars in one pool mesh, each with its own velocity: the reflection off the first
    car's side gets the Doppler shift (k_o - k_i).v/lambda of the reflection point that the
    receiver's image gives (an independent computation), the same as Sionna RT's own for an
    object moving with that car's velocity; the line of sight (static ends) has none."""
    tx, rx = np.array([0.0, 0.0, 1.0]), np.array([40.0, 3.0, 1.0])
    plugin = radio_plugin(tmp_path, tx_position=tx.tolist(), max_depth=1, samples_per_src=20_000,
                          diffraction=False, threads=1)
    ue = position_payload("ue", rx, "pedestrian-phone")
    side = 5.0 - 1.8 / 2  # the side of car1 facing the line: the plane y = 4.1
    image = rx + [0.0, 2 * (side - rx[1]), 0.0]
    point = tx + (image - tx) * (side - tx[1]) / (image[1] - tx[1])  # where tx-image crosses the plane
    # car2 first: car1 takes the mesh's second box (triangles 12-23), so its velocity is found
    # by the box a triangle belongs to, not by the mesh.
    cars = {"car2": ((-60.0, -50.0), (0.0, 20.0)), "car1": ((point[0], 5.0), (8.0, -6.0))}
    msgs = [ue]
    for key, ((x, y), (vx, vy)) in cars.items():
        car = position_payload(key, (x, y, 0.0), "car")
        car.update(heading=0.0, speed=float(np.hypot(vx, vy)), velocity={"x": vx, "y": vy, "z": 0.0},
                   dimensions={"length": 4.5, "width": 1.8, "height": 1.5})
        msgs.append(car)
    step(plugin, 0.0, msgs)
    radio = plugin.radio
    assert len(plugin.pool.objects()) == 2  # both cars in one mesh (and the persons' mesh)
    assert plugin.pool.used["car1"] == ("vehicle", 1)

    def dopplers(paths):
        valid = np.array(paths.valid).ravel().astype(bool)
        tau = np.array(paths.tau).ravel()[valid]
        return np.array(paths.doppler).ravel()[valid][np.argsort(tau)]

    got = dopplers(radio.last_paths)
    k_i = (point - tx) / np.linalg.norm(point - tx)
    k_o = (rx - point) / np.linalg.norm(rx - point)
    expected = float((k_o - k_i) @ np.array([8.0, -6.0, 0.0])) / LAMBDA
    assert len(got) == 2 and got[0] == 0.0  # the line of sight, then the reflection
    assert got[1] == pytest.approx(expected, rel=1e-3)
    assert abs(expected) > 100
    plugin.pool.meshes["vehicle"].velocity = [8.0, -6.0, 0.0]  # Sionna's own, for car1 alone
    np.testing.assert_allclose(dopplers(radio.solve(force=True) and radio.last_paths), got, rtol=1e-4)


def test_doppler_of_the_los_path_is_v_cos_theta_over_lambda(tmp_path):
    tx = np.array([0.0, 0.0, 25.0])
    plugin = radio_plugin(tmp_path, tx_position=tx.tolist(), connected=["car1", "car2"])
    cars = {"car1": ((80.0, 30.0), 0.3, 14.0), "car2": ((-40.0, 60.0), 2.5, 9.0)}
    msgs = []
    for ue, ((x, y), yaw, v) in cars.items():
        m = position_payload(ue, (x, y, 0.0), "car")
        m.update(heading=yaw, speed=v, velocity={"x": v * math.cos(yaw), "y": v * math.sin(yaw), "z": 0.0},
                 dimensions={"length": 4.5, "width": 1.8, "height": 1.5})
        msgs.append(m)
    links = step(plugin, 0.0, msgs)
    for ue, ((x, y), yaw, v) in cars.items():
        antenna = np.array([x, y, 1.5 + 0.1])
        to_tx = (tx - antenna) / np.linalg.norm(tx - antenna)
        vel = v * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        expected = float(vel @ to_tx) / LAMBDA  # approaching the transmitter: positive
        assert links[ue]["los"] and links[ue]["speed"] == pytest.approx(v)
        assert links[ue]["doppler_los_hz"] == pytest.approx(expected, rel=0.01)
        assert abs(expected) > 500  # not a trivially small number


def test_over_nats_sumo_runs_in_its_own_worker_with_the_same_positions(tmp_path, grid, cli):
    cfg = traffic_config(tmp_path, grid)
    cli("run", cfg, "-q", "--out", "inproc", check=0)
    cli("run", cfg, "-q", "--out", "nats", "--set", "transport.kind=nats", check=0)
    a, b = caviar.load_run(tmp_path / "inproc"), caviar.load_run(tmp_path / "nats")
    assert positions(a) == positions(b) and len(positions(a)) > 20
    assert (tmp_path / "nats" / "workers" / "traffic-0.log").exists()


def test_the_osm_traffic_blueprint_runs(tmp_path):
    from conftest import ROOT

    log = caviar.Simulation.from_toml(ROOT / "blueprints" / "osm-traffic" / "config.toml",
                                      overrides={"episode.steps": 3}, out=tmp_path / "run").run()
    traffic = log.topic("3D.mobility.traffic")
    assert traffic["vehicles"].to_list()[-1] > 5 and traffic["persons"].to_list()[-1] > 0
    link = log.topic(LINK)
    assert "uav1" in set(link["UE_Id"]) and set(link["UE_Id"]) <= {"uav1", "passenger6", "passenger10", "passenger24",
                                                                    "passenger31", "passenger36"}
    assert (tmp_path / "run" / "artifacts" / "monitor" / "throughput.png").exists()
