"""The Python/Rust boundary: ``caviar._core``'s typed exports, the wire format and
topic matching shared with the core, run.json's RunStatus and plugins' ``publishes``."""

import ast
import json
import pathlib
import struct
import typing

import numpy as np
import pytest

import caviar
from caviar import _core
from caviar.plugin import Message
from caviar.runlog import RunStatus
from configs import episode, module
from conftest import ROOT, write_config

PKG = ROOT / "python" / "caviar"


def test_the_stub_describes_every_export_and_ships_marked_typed():
    stub = ast.parse((PKG / "_core.pyi").read_text())
    described = set()
    for node in stub.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            described.add(node.name)
        elif isinstance(node, ast.AnnAssign):
            described.add(node.target.id)
        elif isinstance(node, ast.Assign):
            described.update(t.id for t in node.targets)
    exported = {n for n in dir(_core) if not n.startswith("_") or n == "__version__"}
    assert exported <= described, f"not in _core.pyi: {exported - described}"
    for cls in ("Episode", "RawMessage", "StepRequest"):
        members = {n.name for n in next(c for c in stub.body if getattr(c, "name", "") == cls).body
                   if isinstance(n, ast.FunctionDef)}
        public = {n for n in dir(getattr(_core, cls)) if not n.startswith("_")}
        assert public <= members, f"{cls}: not in _core.pyi: {public - members}"
    assert (PKG / "py.typed").exists()


@pytest.mark.parametrize("pattern,topic,expected", [
    ("a.b", "a.b", True), ("a.b", "a.c", False), ("a.*", "a.b", True), ("a.*", "a.b.c", False),
    ("a.>", "a.b.c", True), ("a.>", "a", False), (">", "x", True), ("*.b", "a.b", True),
    ("a", "a.b", False),
])
def test_matching_is_the_cores(pattern, topic, expected):
    assert caviar.matches(pattern, topic) is expected
    assert caviar.matches is _core.matches


@pytest.mark.parametrize("pattern", ["a..b", "", "a.>.b", "a.b*", ".a"])
def test_invalid_patterns_raise_value_error(pattern):
    with pytest.raises(ValueError, match="invalid subscription pattern"):
        caviar.matches(pattern, "a.b")


def _request_frame(step, time, messages, shard=0, shards=1, protocol=2):
    """A step request as the core encodes it (docs/nats-protocol.md), written out here
    as the test's independent reading of the format."""
    header, bodies = [], []
    for topic, kind, body, meta in messages:
        b = body.encode() if isinstance(body, str) else body
        m = {"topic": topic, "kind": kind, "len": len(b), "source": "src", "step": step, "time": time}
        if meta is not None:
            m["meta"] = meta
        header.append(m)
        bodies.append(b)
    head = json.dumps({"protocol": protocol, "step": step, "time": time, "shard": shard, "shards": shards,
                       "messages": header}).encode()
    return struct.pack("<I", len(head)) + head + b"".join(bodies)


def _unpack(frame: bytes):
    (n,) = struct.unpack_from("<I", frame)
    return json.loads(frame[4:4 + n]), frame[4 + n:]


def test_step_frames_round_trip_through_the_core():
    arr = np.arange(3, dtype="<f4")
    meta = json.dumps({"dtype": "<f4", "shape": [3]})
    frame = _request_frame(4, 0.4, [("a.b", "json", '{"x":1}', None), ("img", "binary", arr.tobytes(), meta),
                                    ("f", "artifact", "x.png", None)], shard=1, shards=2)
    req = _core.decode_request(frame)
    assert (req.protocol, req.step, req.time, req.shard, req.shards) == (2, 4, 0.4, 1, 2)
    assert [type(m) for m in req.messages] == [_core.RawMessage] * 3
    msgs = [Message._from_wire(m, pathlib.Path("/run")) for m in req.messages]
    assert msgs[0].data == {"x": 1} and msgs[0].source == "src" and msgs[0].step == 4
    np.testing.assert_array_equal(msgs[1].data, arr)
    assert msgs[2].data == pathlib.Path("/run/x.png") and msgs[2].kind == "artifact"

    out = [("a.b", "json", '{"y":2}', None), ("img", "binary", arr.tobytes(), meta)]
    header, rest = _unpack(_core.encode_reply(out, 0.5, 0.25, rss_mib=12.0, gpu=(40.0, 1024.0)))
    assert header["ok"] is True and header["wall_s"] == 0.5 and header["cpu_s"] == 0.25
    assert (header["rss_mib"], header["gpu_util_pct"], header["gpu_mem_mib"]) == (12.0, 40.0, 1024.0)
    assert [(m["topic"], m["kind"], m["len"], m.get("meta")) for m in header["messages"]] == \
        [("a.b", "json", 7, None), ("img", "binary", 12, meta)]
    assert rest == b'{"y":2}' + arr.tobytes()

    header, rest = _unpack(_core.encode_failure("ValueError: boom", trace="tb"))
    assert header["ok"] is False and header["error"]["message"] == "ValueError: boom" and rest == b""


def test_malformed_or_foreign_requests_are_value_errors():
    with pytest.raises(ValueError, match="protocol 9"):
        _core.decode_request(_request_frame(0, 0.0, [], protocol=9))
    with pytest.raises(ValueError, match="shorter than its length prefix"):
        _core.decode_request(b"\x01")


def test_errors_are_caviars_own_classes(tmp_path):
    with pytest.raises(caviar.ConfigError):
        caviar.Simulation.from_toml(write_config(tmp_path, "[episode]\nts = -1\n"))
    cfg = write_config(tmp_path, episode(0.1, ["s"], steps=5)
                       + module("crash", "s", "sample_plugins:Crash", {"at_step": 1}, params_table=True))
    sim = caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    with pytest.raises(caviar.RunError) as e:
        sim.run()
    assert (e.value.module, e.value.phase, e.value.step) == ("crash", "step", 1)
    status = caviar.load_run(tmp_path / "run").status
    assert (status["status"], status["end_reason"]) == ("failed", "error")


COUNTING = episode(0.1, ["s"], steps=3) + module("count", "s", "sample_plugins:Counter")


def test_run_json_is_a_run_status_and_says_why_the_episode_ended(tmp_path):
    sim = caviar.Simulation.from_toml(write_config(tmp_path, COUNTING), out=tmp_path / "full")
    status = sim.run().status
    fields = typing.get_type_hints(RunStatus)
    assert set(status) <= set(fields) and set(RunStatus.__required_keys__) <= set(status)
    assert (status["status"], status["end_reason"]) == ("completed", "steps")
    assert "ended_by" not in status

    sim = caviar.Simulation.from_toml(write_config(tmp_path, COUNTING), out=tmp_path / "early")
    sim.step()
    sim.close()
    assert caviar.load_run(tmp_path / "early").status["end_reason"] == "closed"
    assert "ended     closed by the host" in caviar.inspect(tmp_path / "early")


WIRING = (episode(0.1, ["s"], steps=3) + module("source", "s", "sample_plugins:Declared")
          + module("sink", "s", "sample_plugins:DeclaredSink"))


def test_validate_warns_about_wiring_from_declared_publishes(tmp_path, cli):
    p = cli("validate", write_config(tmp_path, WIRING), check=0)
    assert "ok (2 modules" in p.stdout
    warnings = [line for line in p.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 2, p.stderr
    assert "modules.sink.subscribe: 'missing.topic' (the plugin's default) — no module publishes it" \
        in warnings[0]
    assert "modules.sink: publishes 'sink.summary' — no module subscribes to it (recorded only)" in warnings[1]

    # A module that declares nothing may publish anything: no subscription is unfed.
    undeclared = WIRING + module("count", "s", "sample_plugins:Counter")
    p = cli("validate", write_config(tmp_path, undeclared, "u.toml"), check=0)
    assert "no module publishes" not in p.stderr and "no module subscribes" in p.stderr


def test_run_prints_the_wiring_warnings_and_strict_refuses_the_run(tmp_path, cli):
    cfg = write_config(tmp_path, WIRING)
    p = cli("run", "-q", cfg, check=0)
    warnings = [line for line in p.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 2 and "'missing.topic'" in warnings[0] and "'sink.summary'" in warnings[1], p.stderr
    runs = sorted((tmp_path / "runs").iterdir())
    assert len(runs) == 1 and json.loads((runs[0] / "run.json").read_text())["status"] == "completed"

    # Strict: the same warnings are one error naming the key, and no run directory is made.
    for args in (("--strict",), ("--set", "episode.strict_wiring=true")):
        p = cli("run", "-q", *args, cfg, check=2)
        first = p.stderr.splitlines()[0]
        assert first.startswith("error: ") and "episode.strict_wiring" in first, p.stderr
        assert "'missing.topic'" in p.stderr and "'sink.summary'" in p.stderr, p.stderr
        assert len(list((tmp_path / "runs").iterdir())) == 1
    p = cli("validate", "--strict", cfg, check=2)
    assert "episode.strict_wiring" in p.stderr

    # From Python: warnings, or ConfigError when strict.
    with pytest.warns(caviar.simulation.WiringWarning) as caught:
        sim = caviar.Simulation.from_toml(cfg, out=tmp_path / "py")
    sim.close()
    assert ["'missing.topic'" in str(w.message) for w in caught] == [True, False], [str(w.message) for w in caught]
    with pytest.raises(caviar.ConfigError, match="strict_wiring"):
        caviar.Simulation.from_toml(cfg, {"episode.strict_wiring": True}, out=tmp_path / "py-strict")
    assert not (tmp_path / "py-strict").exists()


def test_an_invalid_publishes_is_a_config_error(tmp_path, cli):
    cfg = WIRING.replace('sample_plugins:Declared"', 'sample_plugins:BadPublishes"')
    p = cli("validate", write_config(tmp_path, cfg), check=2)
    assert "modules.source.plugin" in p.stderr and "BadPublishes.publishes" in p.stderr
