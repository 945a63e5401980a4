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
from configs import episode, module, output, waypoint_uav
from conftest import ROOT, write_config
from network_configs import WEST, cars_in_the_canyon, ue_reports
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


@pytest.mark.parametrize("sites", [2, 1])
def test_the_radio_network_resumes_to_the_same_messages(tmp_path, cli, sites):
    """Sionna SYS's OLLA offsets, PF history (torch buffers of the scheduler), HARQ outcomes
    and random stream, the handover filters and the last trace (the channel evolves from it
    between refreshes: checkpoints fall between them). With one site both UEs share a cell,
    so the scheduler's history decides, and the shoot cache serves the traces (one source
    per solve): whether it had seen the scene is part of the checkpoint."""
    cfg = write_config(tmp_path, cars_in_the_canyon() if sites == 2 else cars_in_the_canyon(sites=[WEST]))
    kill = random.Random(23).randrange(9, 20)
    log = _resumes_to_the_reference(tmp_path, cli, cfg, [], kill, every=7, steps=24)
    ue = ue_reports(log)
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
    # (the ray-traced network's other keys kept, its scene a name never read)
    cfg = write_config(tmp_path, cars_in_the_canyon(scene="SCENE", channel="38.901-uma"))
    kill = random.Random(26).randrange(9, 20)
    log = _resumes_to_the_reference(tmp_path, cli, cfg, [], kill, every=7, steps=24)
    ue = ue_reports(log)
    assert {u["UE_Id"] for u in ue} == {"car1", "car2"}
    assert all(u["coupling_loss_db"] > 40 for u in ue if u["serving_cell"])


def _slow() -> str:
    """Steps of 50 ms (sample_plugins:Slow in stage pace), for the kill to land on its step."""
    return module("slow", "pace", "sample_plugins:Slow", {"seconds": 0.05})


ENERGY = (episode(1.0, ["mobility", "energy", "mission", "pace"], seed=1)
          + output(name="energy", analysis=["3D.mobility.forecast", "mission.rescue", "mission.result"])
          + _slow() + waypoint_uav(speed=10.0)
          + module("energy", "energy", "uav-energy", {"battery": {"capacity_wh": 1.0, "reserve": 0.2},
                                                      "return_speed_mps": 5.0})
          + module("mission", "mission", "mission", subscribe=["uav.energy", "caviar.episode.end"]))


def test_uav_energy_and_the_flight_home_resume_to_the_same_messages(tmp_path, cli):
    """The battery, the mission's decision and the flight's way home (sent home at t = 5 s)."""
    (tmp_path / "route.csv").write_text("X,Y,Z\n0,0,30\n400,0,30\n")
    config = tmp_path / "energy.toml"
    config.write_text(ENERGY)
    kill = random.Random(43).randrange(7, 13)
    log = _resumes_to_the_reference(tmp_path, cli, config, [], kill, every=3, steps=16)
    assert len(log.decoded("mission.return")) == 1


LIDAR = (episode(0.1, ["mobility", "sensing", "pace"], seed=3)
         + output(name="lidar", analysis=["3D.mobility.forecast", "3D.lidar.*", "3D.lidar.*.sweep"])
         + waypoint_uav(speed=10.0, end_at_last=False)
         + module("car", "mobility", "sample_plugins:CarAt", {"xs": [10.0 + k for k in range(14)]})
         + module("lidar", "sensing", "lidar", {"scene": "scene.xml", "raytracing": {"threads": 1}, "sensor": {
             "channels": 8, "horizontal_resolution_deg": 2.0, "range_noise_m": 0.05, "dropout": 0.1,
             "mount_offset_m": [0.0, 0.0, -1.0]}}, params_table=True)
         + _slow())


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
