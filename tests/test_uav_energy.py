"""UAV energy (issue #43, part 4): the rotary-wing power model against Zeng, Xu and Zhang
(IEEE TWC 2019), the battery step by step through the engine, and the mission sending a
UAV home when its battery would not last the way back."""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest

import caviar
from caviar import _core
from caviar_plugins.energy import Battery, RotaryWing
from configs import episode, module, output, waypoint_uav, write_route

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_hover_power_is_the_papers_168_49_w():
    uav = RotaryWing()
    # Zeng et al., below eq. (12): P0 = 79.86 W and Pi = 88.63 W with Table I's values.
    assert uav.blade_profile_power_w == pytest.approx(79.86, abs=0.005)
    assert uav.induced_power_w == pytest.approx(88.63, abs=0.005)
    assert uav.hover_power_w == pytest.approx(168.49, abs=0.01)
    assert uav.level_power_w(0.0) == pytest.approx(uav.hover_power_w, rel=1e-12)
    assert uav.tip_speed == pytest.approx(120.0) and uav.induced_velocity == pytest.approx(4.03, abs=0.005)


def test_the_maximum_endurance_and_range_speeds_are_the_papers():
    """Minimising P(V) and P(V)/V numerically gives the speeds of the paper's Fig. 3
    (V_me = 10.2 m/s, V_mr = 18.3 m/s); the tangent from the origin touches P at V_mr."""
    uav = RotaryWing()
    v_me, v_mr = uav.max_endurance_speed(), uav.max_range_speed()
    assert v_me == pytest.approx(10.2, abs=0.05)
    assert v_mr == pytest.approx(18.3, abs=0.05)
    h = 1e-4  # at V_mr, dP/dV = P/V
    slope = (uav.level_power_w(v_mr + h) - uav.level_power_w(v_mr - h)) / (2 * h)
    assert slope == pytest.approx(uav.level_power_w(v_mr) / v_mr, rel=1e-4)
    speeds = np.linspace(1.0, 40.0, 400)
    assert speeds[np.argmin(uav.level_power_w(speeds))] == pytest.approx(v_me, abs=0.1)


def test_fast_flight_follows_the_papers_approximation():
    """For V >> v0 the induced term tends to Pi·v0/V (the paper's eq. (13))."""
    uav = RotaryWing()
    for v in (25.0, 35.0):
        approx = (uav.blade_profile_power_w * (1 + 3 * v ** 2 / uav.tip_speed ** 2)
                  + uav.induced_power_w * uav.induced_velocity / v
                  + 0.5 * 0.6 * 1.225 * 0.05 * 0.503 * v ** 3)
        assert uav.level_power_w(v) == pytest.approx(approx, rel=0.005)


def test_climbing_and_speeding_up_cost_what_energy_conservation_says():
    uav = RotaryWing()
    m = 20.0 / 9.80665
    level = uav.level_power_w(5.0)
    assert uav.power_w([3.0, 4.0, 2.0]) == pytest.approx(level + 20.0 * 2.0)  # W·v_z
    assert uav.power_w([3.0, 4.0, -2.0]) == pytest.approx(level)  # no recharge going down
    # From rest to 5 m/s in 0.5 s: ½mV² over the step.
    assert uav.step_power_w([0, 0, 0], [5.0, 0, 0], 0.5) == pytest.approx(level + 0.5 * m * 25 / 0.5)
    assert uav.step_power_w([5.0, 0, 0], [0, 0, 0], 0.5) == pytest.approx(uav.hover_power_w)  # braking is free


FLIGHT = (episode(1.0, ["mobility", "energy", "mission"], seed=1)
          + output(name="energy", analysis=["3D.mobility.forecast", "mission.rescue", "mission.result"])
          + waypoint_uav(speed=10.0)
          + module("energy", "energy", "uav-energy", {"battery": {"capacity_wh": 100.0, "reserve": 0.2},
                                                      "communication_w": 5.0, "computing_w": 10.0})
          + module("mission", "mission", "mission", subscribe=["uav.energy", "caviar.episode.end"]))


def _fly(tmp_path, text: str, route_m: float = 1000.0):
    write_route(tmp_path, [(0, 0, 30), (route_m, 0, 30)])
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text)
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "runs") as sim:
        return sim.run(progress=False)


def test_the_battery_drains_by_the_power_of_each_step(tmp_path):
    log = _fly(tmp_path, FLIGHT)
    energy = [m.data for m in log.decoded("uav.energy")]
    positions = np.array([[m.data["position"][k] for k in "xyz"] for m in log.decoded("3D.mobility.positions")])
    assert len(energy) == len(positions) == 101  # 1,000 m at 10 m/s, from t = 0
    # By hand from the positions: each step's speed, its power (+ 15 W), ½mV² to get going.
    uav = RotaryWing()
    speeds = np.linalg.norm(np.diff(positions, axis=0), axis=1)  # m per 1 s step
    assert np.allclose(speeds, 10.0)
    expected = np.concatenate([[0.0], np.cumsum(uav.level_power_w(speeds) + 15.0)])
    expected[1:] += 0.5 * uav.mass_kg * 10.0 ** 2
    np.testing.assert_allclose([e["energy_wh"] for e in energy], expected / 3600, atol=1e-4)
    np.testing.assert_allclose([e["soc"] for e in energy], 1 - expected / 3600 / 100, atol=1e-5)
    assert energy[5]["propulsion_w"] == pytest.approx(uav.level_power_w(10.0), abs=1e-3)
    # The way home from the far end: 1 km at V_mr, and ½mV_mr² to get going.
    v = uav.max_range_speed()
    home = (0.5 * uav.mass_kg * v ** 2 + 1000.0 / v * (uav.level_power_w(v) + 15.0)) / 3600
    assert energy[-1]["return_wh"] == pytest.approx(home, abs=1e-4)
    assert not any(e["must_return"] for e in energy)
    result = log.decoded("mission.result")[-1].data
    assert result["energy"]["uav1"]["returned_home"] is False
    assert result["energy"]["uav1"]["energy_wh"] == pytest.approx(expected[-1] / 3600, abs=1e-4)
    assert result["energy_per_rescue_wh"] is None  # (no rescue)


def test_the_mission_sends_the_uav_home_and_it_lands_with_its_reserve(tmp_path):
    log = _fly(tmp_path, FLIGHT.replace("capacity_wh = 100.0", "capacity_wh = 6.0"))
    sent = [m for m in log.decoded("mission.return")]
    assert len(sent) == 1 and sent[0].data["UE_Id"] == "uav1"
    assert "battery:" in sent[0].data["reason"]
    energy = [m.data for m in log.decoded("uav.energy")]
    positions = [m.data["position"] for m in log.decoded("3D.mobility.positions")]
    turn = max(range(len(positions)), key=lambda k: positions[k]["x"])
    assert 300.0 < positions[turn]["x"] < 900.0  # it turned before the end of its route
    assert positions[-1] == {"x": 0.0, "y": 0.0, "z": 30.0}  # home
    assert positions[-2]["x"] - positions[-1]["x"] <= RotaryWing().max_range_speed() + 1e-6
    # It lands with its reserve, and not much more: it turned as late as it could.
    assert 0.2 <= energy[-1]["soc"] < 0.2 + 0.03
    end = log.decoded("caviar.episode.end")[-1]
    assert end.data["reason"].startswith("uav1 flew home: battery:")
    result = log.decoded("mission.result")[-1].data
    assert result["energy"]["uav1"]["returned_home"] is True
    # caviar-core report draws it and writes the numbers.
    from caviar_plugins.energy.report import figures

    png, numbers = figures(log, tmp_path / "report")
    assert png.stat().st_size > 20_000
    summary = json.loads(numbers.read_text())["uavs"]["uav1"]
    assert summary["sent_home_at_s"] == sent[0].time and summary["soc"] == energy[-1]["soc"]


def test_a_battery_that_runs_out_ends_the_episode_naming_the_uav(tmp_path):
    text = FLIGHT.replace("capacity_wh = 100.0, reserve = 0.2", "capacity_wh = 2.0, reserve = 0.0").replace(
        'subscribe = ["uav.energy", "caviar.episode.end"]', 'subscribe = ["caviar.episode.end"]')
    log = _fly(tmp_path, text)
    end = log.decoded("caviar.episode.end")[-1]
    assert "uav1's battery ran out" in end.data["reason"]
    assert [m.data["soc"] for m in log.decoded("uav.energy")][-1] == 0.0


@pytest.mark.parametrize("edit, key, says", [
    ("capacity_wh = 100.0", "battery.capacity_wh", "expected a positive number"),
    ("reserve = 0.2", "battery.reserve", "expected a share in [0, initial_soc"),
    ("communication_w = 5.0", "communication_w", "expected a power >= 0"),
    ("computing_w = 10.0", "airframe.weight_n", "expected a positive number"),
    ("computing_w = 10.0", "airframe.air_density", "expected kg/m³ of air"),
])
def test_bad_energy_input_names_the_key_before_anything_runs(tmp_path, capfd, edit, key, says):
    bad = {"battery.capacity_wh": "capacity_wh = 0.0", "battery.reserve": "reserve = 1.5",
           "communication_w": "communication_w = -1.0",
           "airframe.weight_n": "computing_w = 10.0, airframe = { weight_n = -20.0 }",
           "airframe.air_density": "computing_w = 10.0, airframe = { air_density = 1225.0 }"}[key]
    write_route(tmp_path, [(0, 0, 30), (100, 0, 30)])
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(FLIGHT.replace(edit, bad, 1))
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert f"modules.energy.params.{key}:" in first and says in first, first


def test_the_battery_refuses_shares_out_of_range():
    with pytest.raises(ValueError, match="initial_soc"):
        Battery(initial_soc=0.0)
    with pytest.raises(ValueError, match="rotor_solidity"):
        RotaryWing(rotor_solidity=1.5)
    assert math.isclose(Battery().capacity_wh, 100.0)


def test_the_way_home_is_the_straight_3d_line_and_climbs_where_home_is_higher():
    from caviar_plugins.energy import UavEnergy

    plugin = UavEnergy()
    plugin.p = UavEnergy.Params()
    uav = plugin.p.airframe
    v = plugin.return_speed = uav.max_range_speed()
    start = (0.5 * uav.mass_kg * v ** 2) / 3600
    per_second = (uav.level_power_w(v) + 15.0) / 3600
    above = plugin.return_wh(np.array([0.0, 0.0, 90.0]), np.array([0.0, 0.0, 30.0]))  # 60 m straight down
    assert above == pytest.approx(start + 60.0 / v * per_second)
    below = plugin.return_wh(np.array([30.0, 40.0, 10.0]), np.array([0.0, 0.0, 30.0]))  # 50 m, then 20 m up
    assert below == pytest.approx(start + math.dist((30, 40, 10), (0, 0, 30)) / v * per_second + 20.0 * 20.0 / 3600)
    assert plugin.return_wh(np.zeros(3), np.zeros(3)) == 0.0
