"""Link predictions (issue #25, "predictions out"): every step, each UE's link at
horizons ahead, from its forecast or at constant velocity, traced in the step's solve;
checked against the link the run computes later at that position."""

from __future__ import annotations

import json

import numpy as np
import pytest

import caviar
from caviar_plugins.radio.prediction import Forecaster, prediction_errors
from configs import traced_flight
from conftest import write_config


def flight(forecast: int) -> str:
    """The planned Central Park flight, ``forecast`` steps of plan, and its link predicting 0.5, 1 and 2 s ahead."""
    return traced_flight(forecast, predict_horizons_s=[0.5, 1.0, 2.0])


def _flight(tmp_path, name: str, forecast: int):
    cfg = write_config(tmp_path, flight(forecast), f"{name}.toml")
    return caviar.Simulation.from_toml(cfg, out=tmp_path / name).run()


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")  # outputs recorded only
def test_a_prediction_of_a_flight_that_follows_its_plan_is_the_link_computed_later_there(tmp_path):
    """waypoint-flight publishes its plan 4 steps (2 s) ahead; the UAV flies it. The link
    predicted at t for t + h is the link the run computes at t + h (same position, same
    rays), for every horizon that the run reaches; caviar-core report draws it."""
    log = _flight(tmp_path, "plan", forecast=4)
    predictions = [m.data for m in log.decoded("communications.prediction")]
    assert len(predictions) == 8
    assert {p["source"] for m in predictions for p in m["predictions"]} == {"forecast"}
    positions = {round(m.time, 6): m.data["position"] for m in log.decoded("3D.mobility.positions")}
    for m in predictions:
        for p in m["predictions"]:
            if round(p["at_s"], 6) in positions:  # where the UAV then was: where it was predicted to be
                assert p["position"] == pytest.approx(positions[round(p["at_s"], 6)], abs=1e-9)
    errors = prediction_errors(predictions, [(m.time, m.data) for m in log.decoded("communications.link")])
    assert sorted(errors) == [0.5, 1.0, 2.0]
    assert [errors[h]["n"] for h in (0.5, 1.0, 2.0)] == [7, 6, 4]  # the steps whose t + h the run reached
    for h, e in errors.items():
        assert e["path_gain_error_db"]["mean_abs"] < 0.01, (h, e)
        assert e["same_best_pair"] == 1.0 and e["los_transitions"] == e["los_transitions_caught"], (h, e)

    from caviar.report import main as report

    assert report([str(tmp_path / "plan"), "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "prediction.png").stat().st_size > 10_000
    assert (tmp_path / "rep" / "prediction.json").exists()


def test_without_a_plan_the_forecast_is_constant_velocity():
    """No forecast: the first step holds the position, later steps extrapolate the last
    two positions at their velocity, or at the velocity the UE reports (checked by hand);
    a forecast that does not reach a horizon falls back to constant velocity for it."""
    f = Forecaster([0.5, 2.0])
    f.observe("u", 0.0, np.array([0.0, 0.0, 10.0]))
    assert [(s, list(p)) for _, s, p in f.ahead("u", 0.0)] == [("hold", [0.0, 0.0, 10.0])] * 2
    f.observe("u", 0.5, np.array([2.0, 1.0, 10.0]))  # 4 m/s east, 2 m/s north
    (h1, s1, p1), (h2, s2, p2) = f.ahead("u", 0.5)
    assert (s1, s2) == ("constant-velocity", "constant-velocity")
    np.testing.assert_allclose(p1, [4.0, 2.0, 10.0])
    np.testing.assert_allclose(p2, [10.0, 5.0, 10.0])
    f.observe("u", 0.5, np.array([2.0, 1.0, 10.0]), velocity=np.array([0.0, -1.0, 0.5]))  # as reported
    np.testing.assert_allclose(f.ahead("u", 0.5)[1][2], [2.0, -1.0, 11.0])
    f.plan("u", 0.5, [np.array([3.0, 3.0, 10.0]), np.array([4.0, 5.0, 10.0])], ts=0.25)  # 0.5 s of plan
    (_, s1, p1), (_, s2, p2) = f.ahead("u", 0.5)
    assert s1 == "forecast" and list(p1) == [4.0, 5.0, 10.0]
    assert s2 == "constant-velocity"


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")
def test_constant_velocity_predictions_in_the_loop(tmp_path):
    """The same flight without its plan: predictions extrapolate the UAV's last two
    positions; where that lands on the position it then had (a straight stretch), the
    predicted link is the later one, and the error is reported per horizon."""
    log = _flight(tmp_path, "cv", forecast=0)
    predictions = [m.data for m in log.decoded("communications.prediction")]
    assert [p["source"] for p in predictions[0]["predictions"]] == ["hold"] * 3
    assert {p["source"] for m in predictions[1:] for p in m["predictions"]} == {"constant-velocity"}
    pos = {round(m.time, 6): np.array([m.data["position"][k] for k in "xyz"])
           for m in log.decoded("3D.mobility.positions")}
    links = {round(m.time, 6): m.data for m in log.decoded("communications.link")}
    exact = 0
    for m in predictions[1:]:
        t = round(m["time"], 6)
        v = (pos[t] - pos[round(t - 0.5, 6)]) / 0.5
        for p in m["predictions"]:
            expected = pos[t] + v * p["horizon_s"]
            np.testing.assert_allclose([p["position"][k] for k in "xyz"], expected, atol=1e-6)
            later = round(p["at_s"], 6)
            if later in pos and np.linalg.norm(pos[later] - expected) < 1e-6:
                assert p["path_gain_db"] == pytest.approx(links[later]["path_gain_db"], abs=0.01)
                exact += 1
    assert exact >= 3


@pytest.mark.parametrize("edit, key", [
    ("predict_horizons_s = [0.5, 1.0, 2.0]", "predict_horizons_s.1"),
    ("uav_mesh = false", "predict_horizons_s"),
])
def test_bad_predictions_name_the_key(tmp_path, capfd, edit, key):
    from caviar import _core

    replacement = {"predict_horizons_s.1": "predict_horizons_s = [0.5, -1.0]",
                   "predict_horizons_s": "uav_mesh = true"}[key]
    text = flight(0)
    cfg = write_config(tmp_path, text.replace(edit, replacement))
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    err = capfd.readouterr().err
    expected = {"predict_horizons_s.1": "modules.comm.params.predict_horizons_s.1: expected a positive number "
                                        "of seconds, got -1.0",
                "predict_horizons_s": "modules.comm.params: predict_horizons_s needs uav_mesh = false"}[key]
    assert f"{cfg}:" in err and expected in err, err


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")
def test_a_warm_up_at_setup_changes_no_recorded_message(tmp_path):
    """``warm_up_ues`` traces receivers at setup (so a paced run's first steps do not
    compile kernels) and takes them out again: the run records what it records without,
    except that its first step, served by the shoot cache instead of Sionna's recording
    loop, agrees to float32 rounding only (as the cache does, tests/test_shoot_cache.py), and
    its status line for people (caviar.status), which counts the warm-up's solves too."""
    plain = _flight(tmp_path, "plain", forecast=4)
    text = flight(4)
    cfg = write_config(tmp_path, text.replace("uav_mesh = false", "uav_mesh = false\nwarm_up_ues = 4"), "warm.toml")
    warm = caviar.Simulation.from_toml(cfg, out=tmp_path / "warm").run()
    cols = ["step", "source", "topic", "text"]
    a, b = ([r for r in log.messages.select(cols).rows() if r[2] != caviar.STATUS_TOPIC] for log in (warm, plain))
    assert len(warm.topic(caviar.STATUS_TOPIC)) == len(plain.topic(caviar.STATUS_TOPIC)) > 0
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        if x != y:
            assert x[:3] == y[:3] and x[0] == 0, (x, y)
            assert _numbers(json.loads(x[3])) == pytest.approx(_numbers(json.loads(y[3])), rel=1e-6)


def _numbers(value) -> list:
    if isinstance(value, dict):
        return [n for v in value.values() for n in _numbers(v)]
    if isinstance(value, list):
        return [n for v in value for n in _numbers(v)]
    return [float(value)] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")
def test_predictions_next_to_look_ahead_ray_tracing(tmp_path):
    """Look-ahead (its own receivers, UE@k, cached between solves) and predictions (UE#hI)
    in one run: the same predictions and links as without look-ahead."""
    plain = _flight(tmp_path, "plain", forecast=4)
    text = flight(4)
    cfg = write_config(tmp_path, text.replace("uav_mesh = false",
                                              "uav_mesh = false\nlookahead = true\nlookahead_steps = 4"),
                       "ahead.toml")
    ahead = caviar.Simulation.from_toml(cfg, out=tmp_path / "ahead").run()
    for topic in ("communications.prediction", "communications.link"):
        a = [json.dumps(m.data, sort_keys=True) for m in ahead.decoded(topic)]
        b = [json.dumps(m.data, sort_keys=True) for m in plain.decoded(topic)]
        assert len(a) == len(b) == 8
        for x, y in zip(a, b, strict=True):
            assert _numbers(json.loads(x)) == pytest.approx(_numbers(json.loads(y)), rel=1e-4, abs=1e-6)
