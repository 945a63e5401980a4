"""The LiDAR (issue #43, part 1) against geometry computed by hand: the range of each
channel over flat ground, a box at a known distance, a car seen where it moved to, the
motion of the sensor within a sweep, noise and dropout, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

import caviar
from caviar import _core
from caviar_plugins.lidar import COLUMNS, LidarSettings
from caviar_plugins.osm.extrude import Mesh
from caviar_plugins.osm.mitsuba import scene_xml, write_ply

PLUGIN = "lidar"


def _box(x0, y0, x1, y1, h) -> Mesh:
    v = np.array([[x, y, z] for z in (0.0, h) for y in (y0, y1) for x in (x0, x1)], dtype=float)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return Mesh(v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]))


def _scene(tmp_path, building: tuple | None = None) -> str:
    """A flat concrete ground, 2 km wide, at z = 0 and optionally a box building."""
    (tmp_path / "meshes").mkdir(exist_ok=True)
    ground = Mesh(np.array([[-1e3, -1e3, 0], [1e3, -1e3, 0], [1e3, 1e3, 0], [-1e3, 1e3, 0]], dtype=float),
                  np.array([[0, 1, 2], [0, 2, 3]]))
    write_ply(tmp_path / "meshes" / "ground.ply", ground)
    shapes = [("ground", "meshes/ground.ply", "concrete")]
    if building is not None:
        write_ply(tmp_path / "meshes" / "building.ply", _box(*building))
        shapes.append(("building", "meshes/building.ply", "glass"))
    (tmp_path / "scene.xml").write_text(scene_xml(shapes, "test scene"))
    return str(tmp_path / "scene.xml")


RUN = """
[episode]
ts = 0.1
seed = 4
steps = {steps}
stages = ["mobility", "sensing"]

[output]
exclude = ["3D.lidar.*"]

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
params = {{ waypoints = "route.csv", frame = "scene", speed = {speed}, end_at_last = false }}

[modules.lidar]
stage = "sensing"
plugin = "{plugin}"
params = {{ scene = "{scene}", raytracing = {{ threads = 1 }}, sensor = {{ {sensor} }} }}
"""


def _run(tmp_path, scene: str, sensor: str, steps: int = 1, speed: float = 0.0, route=((0, 0, 20), (100, 0, 20)),
         extra: str = ""):
    """Runs a UAV with the LiDAR; returns the sweeps as (metadata, points) in order."""
    (tmp_path / "route.csv").write_text("X,Y,Z\n" + "\n".join(",".join(str(v) for v in p) for p in route) + "\n")
    cfg = tmp_path / "lidar.toml"
    cfg.write_text(RUN.format(steps=steps, speed=speed or 1e-9, plugin=PLUGIN, scene=scene, sensor=sensor) + extra)
    got: list = []
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "runs") as sim:
        while (messages := sim.step()) is not None:
            got += [m for m in messages if m.topic.startswith("3D.lidar.")]
    meta = [m.data for m in got if m.topic.endswith(".sweep")]
    clouds = [np.asarray(m.data) for m in got if not m.topic.endswith(".sweep")]
    return list(zip(meta, clouds, strict=True))


def test_over_flat_ground_each_channel_sees_the_ground_at_h_over_cos_of_its_nadir_angle(tmp_path):
    sensor = ("channels = 16, vertical_fov_deg = [-80.0, -5.0], horizontal_resolution_deg = 1.0, "
              "range_noise_m = 0.0, max_range_m = 400.0, mount_offset_m = [0.0, 0.0, 0.0]")
    ((meta, points),) = _run(tmp_path, _scene(tmp_path), sensor)
    s = LidarSettings(channels=16, vertical_fov_deg=(-80.0, -5.0), horizontal_resolution_deg=1.0)
    assert meta["rays"] == 16 * 360 and meta["points"] == len(points)
    h = 20.0
    nadir = np.radians(90.0 + s.elevations_deg())  # angle from straight down
    expected = h / np.cos(nadir)
    rings = points[:, COLUMNS.index("ring")].astype(int)
    rng = np.linalg.norm(points[:, :3] - [0.0, 0.0, h], axis=1)
    kept = expected <= 400.0
    assert np.array_equal(np.unique(rings), np.flatnonzero(kept))  # beyond max range: no return
    for ch in np.flatnonzero(kept):
        assert np.allclose(rng[rings == ch], expected[ch], rtol=1e-4), ch
        assert (rings == ch).sum() == 360
    np.testing.assert_allclose(points[:, 2], 0.0, atol=1e-3)  # every point on the ground
    # Intensity: concrete's reflectivity times the cosine of the incidence (= of the nadir angle).
    np.testing.assert_allclose(points[:, COLUMNS.index("intensity")], 0.35 * np.cos(nadir[rings]), rtol=1e-3)
    assert meta["objects"] == ["ground"]


def test_a_box_at_a_known_distance(tmp_path):
    """A glass building whose face is 30 m east of the sensor: the horizontal beam toward it
    returns 30 m, the one beside it the ground."""
    sensor = ("channels = 3, vertical_fov_deg = [-10.0, 10.0], horizontal_resolution_deg = 0.5, "
              "range_noise_m = 0.0, mount_offset_m = [0.0, 0.0, 0.0]")
    scene = _scene(tmp_path, building=(30.0, -10.0, 50.0, 10.0, 40.0))
    ((meta, points),) = _run(tmp_path, scene, sensor, route=((0, 0, 20), (-100, 0, 20)))
    ring, obj = points[:, COLUMNS.index("ring")], points[:, COLUMNS.index("object")]
    horizontal = points[(ring == 1)]
    east = horizontal[np.abs(np.arctan2(horizontal[:, 1], horizontal[:, 0])) < 1e-6]
    assert east.shape[0] == 1 and east[0, 0] == pytest.approx(30.0, abs=1e-3)
    # Every horizontal beam within the face's angular extent (±atan(10/30)) hits it at 30/cos(az).
    az = np.arctan2(horizontal[:, 1], horizontal[:, 0])
    on_face = np.abs(az) < math.atan(10 / 30) - 1e-3
    np.testing.assert_allclose(horizontal[on_face, 0], 30.0, atol=1e-3)
    np.testing.assert_allclose(np.hypot(horizontal[on_face, 0], horizontal[on_face, 1]), 30.0 / np.cos(az[on_face]),
                               rtol=1e-5)
    names = meta["objects"]
    assert {names[int(k)] for k in obj[ring == 1][on_face[: (ring == 1).sum()]]} == {"building"}
    # Glass reflects little at 905 nm: its returns are the faintest.
    glass = points[obj == names.index("building"), COLUMNS.index("intensity")]
    assert glass.max() <= 0.05 + 1e-6


def test_a_moving_car_is_seen_at_its_new_position_in_the_next_sweep(tmp_path):
    """A SUMO-sized car (4.5 × 1.8 × 1.5 m) published by a module at x = 20 m, then 25 m:
    the sensor's horizontal beam at the car's height meets its rear face at x − 2.25 m."""
    sensor = ("channels = 1, vertical_fov_deg = [0.0, 0.0], horizontal_resolution_deg = 1.0, rate_hz = 10.0, "
              "range_noise_m = 0.0, mount_offset_m = [0.0, 0.0, 0.0]")
    extra = """
[modules.car]
stage = "mobility"
plugin = "sample_plugins:CarAt"
params = { xs = [20.0, 25.0], height = 1.5 }
"""
    sweeps = _run(tmp_path, _scene(tmp_path), sensor, steps=2, route=((0, 0, 1.0), (-100, 0, 1.0)), extra=extra)
    assert [m["sweep"] for m, _ in sweeps] == [0, 1]
    for (meta, points), x in zip(sweeps, (20.0, 25.0), strict=True):
        toward = points[np.abs(np.arctan2(points[:, 1], points[:, 0])) < 1e-6]
        assert toward[0, 0] == pytest.approx(x - 2.25, abs=1e-3)
        assert meta["objects"][int(toward[0, COLUMNS.index("object")])] == "car1"


def test_a_moving_sensor_fires_each_column_from_where_it_is(tmp_path):
    """At 10 m/s a 0.1 s sweep spans 1 m: the column fired at azimuth 180° (halfway) starts
    0.5 m further east than the first, so a wall west of the route reads 0.5 m more."""
    sensor = ("channels = 1, vertical_fov_deg = [0.0, 0.0], horizontal_resolution_deg = 90.0, rate_hz = 10.0, "
              "range_noise_m = 0.0, mount_offset_m = [0.0, 0.0, 0.0]")
    scene = _scene(tmp_path, building=(-60.0, -50.0, -40.0, 50.0, 40.0))
    sweeps = _run(tmp_path, scene, sensor, steps=3, speed=10.0, route=((0, 0, 20), (100, 0, 20)))
    meta, points = sweeps[-1]  # (the first steps give the velocity)
    west = points[np.isclose(np.abs(np.arctan2(points[:, 1], points[:, 0])), math.pi, atol=1e-4)]
    start = meta["origin"][0]
    # Fired half a sweep after the start, 0.5 m east of it; the wall's face at x = −40.
    assert west[0, 0] == pytest.approx(-40.0, abs=1e-3)
    assert meta["time"] == pytest.approx(0.2) and start == pytest.approx(2.0, abs=1e-6)
    assert np.linalg.norm(west[0, :3] - [start + 0.5, 0, 20]) == pytest.approx(start + 0.5 + 40.0, abs=1e-3)


def test_noise_and_dropout_have_the_asked_statistics(tmp_path):
    sensor = ("channels = 8, vertical_fov_deg = [-60.0, -30.0], horizontal_resolution_deg = 0.5, "
              "range_noise_m = 0.05, dropout = 0.2, mount_offset_m = [0.0, 0.0, 0.0]")
    ((meta, points),) = _run(tmp_path, _scene(tmp_path), sensor)
    n = 8 * 720
    assert meta["points"] + meta["dropped"] == n
    assert abs(meta["dropped"] / n - 0.2) < 4 * math.sqrt(0.2 * 0.8 / n)  # within 4 sigma
    s = LidarSettings(channels=8, vertical_fov_deg=(-60.0, -30.0))
    rings = points[:, COLUMNS.index("ring")].astype(int)
    expected = 20.0 / np.sin(-np.radians(s.elevations_deg()))[rings]
    error = np.linalg.norm(points[:, :3] - [0, 0, 20], axis=1) - expected
    assert abs(error.mean()) < 4 * 0.05 / math.sqrt(len(error))
    assert error.std() == pytest.approx(0.05, rel=0.05)


@pytest.mark.parametrize("sensor, key, says", [
    ("channels = 0", "sensor.channels", "expected a whole number of beams >= 1"),
    ("vertical_fov_deg = [-100.0, 90.0]", "sensor.vertical_fov_deg", "at most 180°"),
    ("horizontal_resolution_deg = 0.7", "sensor.horizontal_resolution_deg", "divides 360"),
    ("dropout = 1.0", "sensor.dropout", "probability in [0, 1)"),
    ("rate_hz = 0.0", "sensor.rate_hz", "expected a positive number"),
])
def test_bad_lidar_input_names_the_key_before_anything_runs(tmp_path, capfd, sensor, key, says):
    (tmp_path / "route.csv").write_text("X,Y,Z\n0,0,20\n10,0,20\n")
    cfg = tmp_path / "lidar.toml"
    cfg.write_text(RUN.format(steps=1, speed=1.0, plugin=PLUGIN, scene="empty", sensor=sensor))
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert f"modules.lidar.params.{key}:" in first and says in first, first


def test_the_view_draws_the_sweep_as_one_cloud_per_colour_and_the_state_of_charge(tmp_path, browser):
    """caviar-core view: the LiDAR's view.lidar points (thinned to view_points) in a few
    THREE.Points, and the energy plugin's state-of-charge label beside the UAV."""
    from caviar.view import start_server
    from view_support import open_page

    sensor = "channels = 16, vertical_fov_deg = [-60.0, -5.0], horizontal_resolution_deg = 1.0, range_noise_m = 0.0"
    extra = """
[modules.energy]
stage = "sensing"
plugin = "uav-energy"
params = { battery = { capacity_wh = 50.0 } }
"""
    scene = _scene(tmp_path, building=(30.0, -10.0, 50.0, 10.0, 40.0))
    text = RUN.format(steps=3, speed=5.0, plugin=PLUGIN, scene=scene, sensor=sensor).replace(
        "threads = 1 },", "threads = 1 }, view_points = 500,") + extra
    (tmp_path / "route.csv").write_text("X,Y,Z\n0,0,20\n100,0,20\n")
    (tmp_path / "lidar.toml").write_text(text)
    with caviar.Simulation.from_toml(tmp_path / "lidar.toml", out=tmp_path / "run") as sim:
        log = sim.run(progress=False)
    drawn = log.decoded("view.lidar")[-1].data["points"]
    assert len(drawn) == 500 and {p["color"] for p in drawn} == {"#7cb342", "#b0bec5"}  # ground, building
    label = log.decoded("view.energy")[-1].data["labels"][0]
    assert label["text"].startswith("uav1 ") and label["text"].endswith(" %") and label["z"] == pytest.approx(23.0)
    srv = start_server(tmp_path / "run", pending=False)
    try:
        page, errors = open_page(browser, srv.url)
        page.wait_for_function("caviarView.viewPrimitives > 0", timeout=20_000)  # (at step 0)
        assert page.evaluate("caviarView.viewPrimitives") == 500 + 1  # the points and the label
        assert page.evaluate("caviarView.viewObjects") == 2 + 1  # two clouds (two colours) and the label
        assert not errors
        page.close()
    finally:
        srv.stop()
