"""The Python face of the engine: plugins in-process, stepping, payloads, errors."""

import json

import numpy as np
import pytest

import caviar
from configs import episode, module, run_config, write_route
from conftest import write_config

BASE = episode(0.5, ["first", "second"], steps=4, seed=11)
NOISE_ECHO = module("noise", "first", "sample_plugins:Noise") + module("echo", "second", "sample_plugins:Echo")


def test_step_by_step_visibility_between_stages(tmp_path):
    cfg = write_config(tmp_path, BASE
                       + module("b", "second", "sample_plugins:Counter", {"topic": "count.b"}, subscribe=["count.a"])
                       + module("a", "first", "sample_plugins:Counter", {"topic": "count.a", "label": "A"},
                                subscribe=["count.b"]))
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "run") as sim:
        first = sim.step()
        assert [(m.topic, m.source, m.step) for m in first] == [("count.a", "a", 0), ("count.b", "b", 0)]
        # b (later stage) saw a's message of the same step; a sees b's only next step.
        assert first[1].data["seen"] == 1
        assert first[0].data == {"step": 0, "t": 0.0, "label": "A", "seen": 0, "value": 0.0}
        second = sim.step()
        assert second[0].data["seen"] == 1 and second[1].data["seen"] == 1
        assert sim.steps_done == 2 and sim.time == 1.0
        log = sim.run()
    assert sim.done and sim.step() is None
    assert log.status["status"] == "completed"
    assert log.messages.height == 8
    frame = log.topic("count.*")
    assert frame["step"].to_list() == [0, 0, 1, 1, 2, 2, 3, 3]
    assert frame["payload.step"].to_list() == frame["step"].to_list()
    assert frame["value"].to_list() == [0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0]


def test_periods_and_offsets_for_python_plugins(tmp_path):
    log = run_config(tmp_path, episode(0.5, ["first", "second"], steps=7, seed=11)
                     + module("fast", "first", "sample_plugins:Counter", {"topic": "fast"})
                     + module("slow", "second", "sample_plugins:Counter", {"topic": "slow"}, every=3, offset=2,
                              subscribe=["fast"]))
    slow = log.topic("slow")
    assert slow["step"].to_list() == [2, 5]
    # At step 2 it has fast's messages of steps 0, 1, 2; at step 5 those of 3, 4, 5.
    assert slow["seen"].to_list() == [3, 3]
    times = log.module_times()
    assert dict(zip(times["module"], times["steps"], strict=True)) == {"fast": 7, "slow": 2, "caviar.core": 7}
    # Resident memory of this (Python + numpy + polars) process: tens of MiB at least, below 20 GiB.
    assert all(20 < m < 20_000 for m in times["max_rss_mib"]), times
    assert (times["cpu_s"] >= 0).all() and (times["wall_s"] > 0).all()


def test_binary_payloads_keep_dtype_and_shape_and_never_touch_json(tmp_path):
    log = run_config(tmp_path, BASE + NOISE_ECHO)
    arrays = log.decoded("noise.array")
    echoed = log.decoded("echo.noise.array")
    assert len(arrays) == len(echoed) == 4
    for a, e, j in zip(arrays, echoed, log.decoded("noise.json"), strict=False):
        assert a.kind == "binary" and a.data.dtype == np.complex64 and a.data.shape == (4,)
        np.testing.assert_array_equal(a.data, e.data)
        np.testing.assert_allclose(a.data, np.asarray(j.data["x"], dtype=np.complex64) * 1j)
    kinds = dict(zip(log.messages["topic"], log.messages["kind"], strict=True))
    assert kinds == {"noise.json": "json", "noise.array": "binary", "echo.noise.json": "json",
                     "echo.noise.array": "binary"}
    row = log.messages.filter(log.messages["topic"] == "noise.array").row(0, named=True)
    assert row["text"] is None and json.loads(row["meta"]) == {"dtype": "<c8", "shape": [4]}


@pytest.mark.parametrize("transport", ["in-process", "nats"])
def test_tables_travel_as_arrow_and_come_back_as_dataframes(tmp_path, transport, monkeypatch):
    import polars as pl

    from configs import caviar_env, nats_transport

    monkeypatch.setenv("PYTHONPATH", caviar_env()["PYTHONPATH"])  # (the workers import the test plugins)
    text = (BASE + (nats_transport() if transport == "nats" else "")
            + module("tables", "first", "sample_plugins:Tables")
            + module("echo", "second", "sample_plugins:Echo", subscribe=["tables.>"]))
    log = run_config(tmp_path, text)
    tables, echoed = log.decoded("tables.draws"), log.decoded("echo.tables.draws")
    assert len(tables) == len(echoed) == 4
    for a, e in zip(tables, echoed, strict=True):
        assert a.kind == "binary" and isinstance(a.data, pl.DataFrame) and a.data.equals(e.data)
        assert a.data["name"].to_list() == ["a", None, "c"] and a.data.schema["pair"] == pl.Array(pl.Float64, 2)
        np.testing.assert_array_equal(a.data["pair"].to_numpy()[:, 1], 2 * a.data["x"].to_numpy())
    row = log.messages.filter(log.messages["topic"] == "tables.draws").row(0, named=True)
    assert row["text"] is None and json.loads(row["meta"]) == {"content_type": "application/vnd.apache.arrow.stream"}


def test_artifacts_travel_as_paths_relative_to_the_run_directory(tmp_path):
    log = run_config(tmp_path, BASE + module("writer", "first", "sample_plugins:WritesFile")
                     + module("reader", "second", "sample_plugins:Reader"))
    assert log.messages.filter(log.messages["topic"] == "files.frame")["text"].to_list()[0] == \
        "artifacts/writer/frame-000.txt"
    assert log.topic("files.read")["text"].to_list() == [f"t={0.5 * k}" for k in range(4)]


def test_same_seed_same_messages_other_seed_other_messages(tmp_path):
    cfg = write_config(tmp_path, BASE + NOISE_ECHO)
    runs = [caviar.Simulation.from_toml(cfg, out=tmp_path / f"r{i}").run().messages for i in range(2)]
    assert runs[0].equals(runs[1])
    other = caviar.Simulation.from_toml(cfg, overrides={"episode.seed": 12}, out=tmp_path / "r3").run().messages
    assert not other.equals(runs[0])
    assert other.select("step", "topic", "source").equals(runs[0].select("step", "topic", "source"))


def test_a_crashing_plugin_raises_run_error_and_keeps_the_log(tmp_path):
    cfg = write_config(tmp_path, episode(0.5, ["first", "second"], steps=50, seed=11)
                       + module("crash", "second", "sample_plugins:Crash", {"at_step": 3}))
    sim = caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    with pytest.raises(caviar.RunError) as err:
        sim.run()
    e = err.value
    assert (e.module, e.phase, e.step) == ("crash", "step", 3)
    assert "ZeroDivisionError" in str(e) and "sample_plugins.py" in str(e)  # the traceback
    log = caviar.load_run(e.run_dir)
    assert log.status["status"] == "failed"
    assert log.status["error"]["module"] == "crash" and log.status["error"]["step"] == 3
    assert "ZeroDivisionError" in log.status["error"]["trace"]
    assert log.topic("crash.alive")["step"].to_list() == [0, 1, 2]


def test_a_bad_payload_names_the_topic(tmp_path):
    cfg = write_config(tmp_path, BASE + module("bad", "first", "sample_plugins:BadPayload"))
    with pytest.raises(caviar.RunError, match="payload on topic 'bad.payload' is not JSON-serialisable"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run").run()


@pytest.mark.parametrize("module_table, key, line, expected", [
    ('plugin = "sample_plugins:Counter"\nparams = { topc = "x" }', "modules.m.params.topc", 11,
     "unknown parameter 'topc' of Counter"),
    ('plugin = "sample_plugins:Counter"\n[modules.m.params]\nscale = "big"', "modules.m.params.scale", 12,
     "expected float, got str 'big'"),
    ('plugin = "sample_plugins:Nope"', "modules.m.plugin", 10, "has no 'Nope'"),
    ('plugin = "no_such_package.mod:X"', "modules.m.plugin", 10, "cannot import 'no_such_package.mod'"),
    ('plugin = "sample_plugins:NotAPlugin"', "modules.m.plugin", 10, "not a subclass of caviar.Plugin"),
    ('plugin = "not-installed-entry-point"', "modules.m.plugin", 10, "no plugin named 'not-installed-entry-point'"),
])
def test_plugin_config_errors_name_file_line_and_key(tmp_path, module_table, key, line, expected):
    cfg = write_config(tmp_path, BASE + f'\n[modules.m]\nstage = "first"\n{module_table}\n')
    with pytest.raises(caviar.ConfigError) as err:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    text = str(err.value)
    assert text.startswith(f"{cfg}:{line}: {key}: "), text
    assert expected in text, text
    assert not (tmp_path / "run").exists(), "a config error must not start a run"


def test_entry_point_plugins_are_found_by_name(tmp_path):
    write_route(tmp_path, [(0, 0, 10), (10, 0, 10)], "path.csv")
    log = run_config(tmp_path, BASE + module("uav", "first", "waypoint-flight", {
        "frame": "scene", "waypoints": "path.csv", "speed": 2.0, "end_at_last": False}))
    pos = log.topic("3D.mobility.positions")["position"].struct.field("x").to_list()
    assert pos == [0.0, 1.0, 2.0, 3.0]  # 2 m/s at Ts = 0.5 s
