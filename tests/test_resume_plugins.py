"""The built-in plugins resume (issue #28): each blueprint family, killed with SIGKILL at a
random step and resumed from its last checkpoint, records exactly the messages of an
uninterrupted run with the same seed, bit for bit and in the same order.

The search-and-rescue mission (flight, camera, beam selection, ray-traced link, image
link, detector, mission), the radio network (Sionna SYS's link adaptation and
scheduler, handover, ray-traced channels evolving between traces), SUMO traffic with
the traffic link (SUMO's saved state, scatterer pools that grew) and the ray-traced
link with the shoot cache, prediction and look-ahead. One Dr.Jit thread, as
determinism asks."""

from __future__ import annotations

import pathlib
import random

import pytest

import caviar
from conftest import ROOT, write_config
from test_resume import _kill_at, _messages

BLUEPRINTS = ROOT / "blueprints"


def _resumes_to_the_reference(tmp_path, cli, config: pathlib.Path, sets: list[str], kill: int, every: int,
                              steps: int):
    """Reference run, a run killed once step ``kill`` started, its resume; the recorded
    messages of the two must be equal."""
    sets = [*sets, "--set", f"output.checkpoint_every={every}", "--set", f"episode.steps={steps}"]
    cli("run", config, *sets, "-q", "--out", tmp_path / "reference", check=0)
    _kill_at([str(config), *sets], tmp_path / "run", kill, tmp_path)
    assert caviar.load_run(tmp_path / "run").status["status"] in ("abandoned", "failed")
    p = cli("run", "--resume", tmp_path / "run", "-q", check=0)
    assert "resumed at step" in p.stderr, p.stderr
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "completed" and s["steps_done"] == steps, s
    # The resume went on from a checkpoint, not from the start.
    assert len(s["resumed_at"]) == 1 and every <= s["resumed_at"][0] <= kill + 1, (s["resumed_at"], kill)
    ref, got = _messages(tmp_path / "reference"), _messages(tmp_path / "run")
    assert got.height == ref.height > steps
    assert got.equals(ref)  # every message, bit for bit, in the same order
    return caviar.load_run(tmp_path / "run")


def test_the_sar_mission_resumes_to_the_same_messages(tmp_path, cli):
    """Every plugin of the main job: random beams (ctx.rng), packet loss (ctx.rng),
    the detector's positions, the mission's rescues, the UAV body in the ray-traced scene."""
    sets = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "--set",
            "modules.comm.params.raytracing.threads=1",
            "--set", 'modules.beams.params.method="random"']
    kill = random.Random(28).randrange(4, 9)
    log = _resumes_to_the_reference(tmp_path, cli, BLUEPRINTS / "sar" / "config.toml", sets, kill, every=3,
                                    steps=11)
    assert set(log.messages["topic"]) >= {"ai.beam.selection", "ai.image_quality", "ai.detections",
                                          "communications.throughput", "3D.mobility.positions"}


NETWORK = """
[episode]
ts = 0.02
seed = 3
stages = ["mobility", "communications"]

[modules.ues]
stage = "mobility"
plugin = "sample_plugins:LineMover"
[[modules.ues.params.ues]]
id = "car1"
start = [-20.0, 2.0, 0.0]
end = [60.0, 2.0, 0.0]
speed = 15.0
[[modules.ues.params.ues]]
id = "car2"
start = [50.0, -2.0, 0.0]
end = [-30.0, -2.0, 0.0]
speed = 10.0

[modules.net]
stage = "communications"
plugin = "radio-network"
[modules.net.params]
channel = "ray-traced"
subcarrier_spacing_hz = 30e3
harq_processes = 4
subbands = 4
handover = { time_to_trigger_s = 0.04 }
scene = "SCENE"
raytracing = { max_depth = 2, samples_per_src = 5000, threads = 1 }
evolution = { refresh_s = 0.1 }
[[modules.net.params.sites]]
name = "west"
position = [-80.0, 0.0, 10.0]
azimuths_deg = [0.0]
[[modules.net.params.sites]]
name = "east"
position = [80.0, 0.0, 10.0]
azimuths_deg = [180.0]
"""


@pytest.mark.parametrize("sites", [2, 1])
def test_the_radio_network_resumes_to_the_same_messages(tmp_path, cli, sites):
    """Sionna SYS's OLLA offsets, PF history (torch buffers of the scheduler), HARQ outcomes
    and random stream, the handover filters and the last trace (the channel evolves from it
    between refreshes: checkpoints fall between them). With one site both UEs share a cell,
    so the scheduler's history decides, and the shoot cache serves the traces (one source
    per solve): whether it had seen the scene is part of the checkpoint."""
    import sionna.rt as rt

    text = NETWORK.replace("SCENE", pathlib.Path(rt.scene.simple_street_canyon).as_posix())
    if sites == 1:
        text = text[:text.index('[[modules.net.params.sites]]\nname = "east"')]
    cfg = write_config(tmp_path, text)
    kill = random.Random(23).randrange(9, 20)
    log = _resumes_to_the_reference(tmp_path, cli, cfg, [], kill, every=7, steps=24)
    ue = [m.data for m in log.decoded("network.ue")]
    assert {u["UE_Id"] for u in ue} == {"car1", "car2"} and all("mcs" in u for u in ue if u["serving_cell"])


def test_sumo_traffic_and_the_traffic_link_resume_to_the_same_messages(tmp_path, cli):
    """SUMO's own saved state (with its random streams), the connected cars' receivers
    and the scatterer pools, grown past their first size before the checkpoint."""
    sets = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "--set",
            "modules.comm.params.raytracing.threads=1",
            "--set", "modules.comm.params.vehicle_pool=4", "--set", "modules.comm.params.person_pool=2",
            "--set", "modules.traffic.params.pedestrians=0"]
    kill = random.Random(24).randrange(5, 8)
    log = _resumes_to_the_reference(tmp_path, cli, BLUEPRINTS / "osm-traffic" / "config.toml", sets, kill,
                                    every=4, steps=9)
    assert log.topic("3D.mobility.traffic")["vehicles"].max() > 4


def test_the_ray_traced_link_with_shoot_cache_prediction_and_look_ahead_resumes(tmp_path, cli):
    """Without UAV bodies the scene is static: the shoot cache serves every solve after
    the first, look-ahead serves steps from its cached traces and prediction forecasts
    from the flight's plan. A resumed run must see the cache's geometry again so that its
    next solve is served as the uninterrupted run's was."""
    sets = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "--set",
            "modules.comm.params.raytracing.threads=1",
            "--set", "modules.comm.params.uav_mesh=false", "--set", "modules.comm.params.raytracing.shoot_cache=true",
            "--set", "modules.comm.params.lookahead=true", "--set", "modules.comm.params.lookahead_steps=2",
            "--set", "modules.comm.params.predict_horizons_s=[0.5, 1.0]"]
    kill = random.Random(25).randrange(5, 9)
    _resumes_to_the_reference(tmp_path, cli, BLUEPRINTS / "raytraced" / "config.toml", sets, kill, every=3, steps=11)


def test_the_radio_network_on_the_38901_channel_resumes_to_the_same_messages(tmp_path, cli):
    """The TR 38.901 channel: every UE's LOS state and shadow fading per site, and the
    random state of Sionna's draws (seeded from the call count) are in the checkpoint."""
    text = NETWORK.replace('channel = "ray-traced"', 'channel = "38.901-uma"')
    cfg = write_config(tmp_path, text)
    kill = random.Random(26).randrange(9, 20)
    log = _resumes_to_the_reference(tmp_path, cli, cfg, [], kill, every=7, steps=24)
    ue = [m.data for m in log.decoded("network.ue")]
    assert {u["UE_Id"] for u in ue} == {"car1", "car2"}
    assert all(u["coupling_loss_db"] > 40 for u in ue if u["serving_cell"])


ENERGY = """
[episode]
ts = 1.0
seed = 1
stages = ["mobility", "energy", "mission", "pace"]

[output]
name = "energy"
analysis = ["3D.mobility.forecast", "mission.rescue", "mission.result"]

[modules.slow]             # (steps of 50 ms, for the kill to land on its step)
stage = "pace"
plugin = "sample_plugins:Slow"
params = { seconds = 0.05 }

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
params = { waypoints = "route.csv", frame = "scene", speed = 10.0 }

[modules.energy]
stage = "energy"
plugin = "uav-energy"
params = { battery = { capacity_wh = 1.0, reserve = 0.2 }, return_speed_mps = 5.0 }

[modules.mission]
stage = "mission"
plugin = "mission"
subscribe = ["uav.energy", "caviar.episode.end"]
"""


def test_uav_energy_and_the_flight_home_resume_to_the_same_messages(tmp_path, cli):
    """The battery, the mission's decision and the flight's way home (sent home at t = 5 s)."""
    (tmp_path / "route.csv").write_text("X,Y,Z\n0,0,30\n400,0,30\n")
    config = tmp_path / "energy.toml"
    config.write_text(ENERGY)
    kill = random.Random(43).randrange(7, 13)
    log = _resumes_to_the_reference(tmp_path, cli, config, [], kill, every=3, steps=16)
    assert len(log.decoded("mission.return")) == 1


LIDAR = """
[episode]
ts = 0.1
seed = 3
stages = ["mobility", "sensing", "pace"]

[output]
name = "lidar"
analysis = ["3D.mobility.forecast", "3D.lidar.*", "3D.lidar.*.sweep"]

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
params = { waypoints = "route.csv", frame = "scene", speed = 10.0, end_at_last = false }

[modules.car]
stage = "mobility"
plugin = "sample_plugins:CarAt"
params = { xs = [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0, 17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0] }

[modules.lidar]
stage = "sensing"
plugin = "lidar"
[modules.lidar.params]
scene = "scene.xml"
raytracing = { threads = 1 }
[modules.lidar.params.sensor]
channels = 8
horizontal_resolution_deg = 2.0
range_noise_m = 0.05
dropout = 0.1
mount_offset_m = [0.0, 0.0, -1.0]

[modules.slow]             # (steps of 50 ms, for the kill to land on its step)
stage = "pace"
plugin = "sample_plugins:Slow"
params = { seconds = 0.05 }
"""


def test_the_lidar_resumes_to_the_same_point_clouds(tmp_path, cli):
    """Noise and dropout (ctx.rng), the car's box in the pool, the sensor's velocity."""
    from test_lidar import _scene

    _scene(tmp_path, building=(30.0, -10.0, 50.0, 10.0, 40.0))
    (tmp_path / "route.csv").write_text("X,Y,Z\n0,0,2\n-100,0,2\n")
    config = tmp_path / "lidar.toml"
    config.write_text(LIDAR)
    kill = random.Random(431).randrange(6, 11)
    log = _resumes_to_the_reference(tmp_path, cli, config, [], kill, every=3, steps=14)
    assert len(log.decoded("3D.lidar.uav1")) == 14
    assert "car1" in log.decoded("3D.lidar.uav1.sweep")[-1].data["objects"]
