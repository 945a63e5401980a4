"""Issue 13 D6: a stranger on the run's NATS server cannot steer the run.

A real run (spawned nats-server, real `caviar worker` processes) while a stranger
connection injects forgeries: each is refused by the worker it reaches, logged and
counted in run.json, and the recorded messages equal those of the same run in-process.
"""

import asyncio
import json
import os
import pathlib
import subprocess
import sys
import time

import pytest

import caviar
from caviar import _core
from configs import episode, module, nats_transport
from conftest import write_config
from test_nats import env, start_run, wait_for_steps, worker_pids

CONFIG = (episode(0.1, ["a", "b"], steps=120) + nats_transport()
          + module("slow", "a", "sample_plugins:Slow", {"seconds": 0.03}, params_table=True)
          + module("count", "b", "sample_plugins:Counter"))


def proc_env(pid: int) -> dict[str, str]:
    raw = pathlib.Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(kv.decode().split("=", 1) for kv in raw if b"=" in kv)


def server_url(run_dir: pathlib.Path) -> str:
    log = (run_dir / "nats-server.log").read_text()
    port = int(log.split("Listening for client connections on 127.0.0.1:")[1].split()[0])
    return f"nats://127.0.0.1:{port}"


def step_frame(step: int) -> bytes:
    """A well-formed step request (protocol 2 header, no messages), unsealed."""
    head = json.dumps({"protocol": _core.PROTOCOL, "step": step, "time": step * 0.1, "shard": 0, "shards": 1,
                       "messages": []}).encode()
    return len(head).to_bytes(4, "little") + head


async def stranger(url: str, user: str, password: str, run: str, key: str) -> dict:
    """Connects without and then with the run's credentials (but without its key) and
    injects every forgery; returns what it saw. `key` (the run key) is used only for
    the last two frames, to show the checks behind the MAC: a key holder's frames with
    a fresh sequence number that are still refused."""
    import nats
    import nats.errors

    seen: dict = {}
    try:
        await nats.connect(url, allow_reconnect=False, max_reconnect_attempts=0, connect_timeout=2)
        seen["anonymous"] = "connected"
    except Exception as e:  # the server of the run requires its credentials
        seen["anonymous"] = f"{type(e).__name__}: {e}"

    nc = await nats.connect(url, user=user, password=password)
    captured: list = []

    async def capture(msg):
        captured.append(msg)

    # An insider observes the traffic (no TLS): it captures genuine step frames.
    await nc.subscribe(f"caviar.{run}.slow.step", cb=capture)
    await nc.flush()
    for _ in range(200):
        if captured:
            break
        await asyncio.sleep(0.02)
    genuine = captured[0].data
    inbox = nc.new_inbox()
    answers: list = []

    async def answered(msg):
        answers.append(msg)

    await nc.subscribe(inbox, cb=answered)
    subject = f"caviar.{run}.slow.step"
    other_key = os.urandom(32).hex()
    forgeries = [
        # A forged step with a big step number: unsealed, with a made-up trailer, and sealed
        # with a key of its own (a valid-looking MAC under the wrong key).
        (subject, step_frame(10**6) + os.urandom(40), inbox),
        (subject, _core.sign(other_key, run, subject, 10**9, step_frame(10**6)), inbox),
        # A genuine frame captured and sent again.
        (subject, genuine, inbox),
        # The genuine frame on another module's subject.
        (f"caviar.{run}.count.step", genuine, inbox),
        # A stop, and a teardown without a reply subject.
        (f"caviar.{run}.stop", b"{}", None),
        (f"caviar.{run}.slow.slow-0.teardown", b"{}", None),
    ]
    # With the key, a sequence number the core will not reach in this run: a step past
    # the end of the episode, and a teardown without a reply subject.
    seq = _core.verify(key, run, subject, genuine)[0] + 2000
    teardown = f"caviar.{run}.slow.slow-0.teardown"
    forgeries += [
        (subject, _core.sign(key, run, subject, seq, step_frame(10**6)), inbox),
        (teardown, _core.sign(key, run, teardown, seq + 1, b"{}"), None),
    ]
    for subj, data, reply in forgeries:
        if reply:
            await nc.publish(subj, data, reply=reply)
        else:
            await nc.publish(subj, data)
    await nc.flush()
    await asyncio.sleep(0.5)
    seen["answers"] = len(answers)
    await nc.close()
    return seen


def test_forged_replayed_and_misdirected_frames_are_refused_recorded_and_change_nothing(tmp_path, cli):
    run = start_run(tmp_path, CONFIG)
    try:
        wait_for_steps(run, tmp_path / "run", 5)
        (pid,) = worker_pids("slow")
        worker_env = proc_env(pid)
        user, password, key = worker_env["NATS_USER"], worker_env["NATS_PASSWORD"], worker_env["CAVIAR_RUN_KEY"]
        # The secrets reach the workers by environment, never on the command line.
        cmdline = pathlib.Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        assert "--module\0slow" in cmdline
        assert password not in cmdline and key not in cmdline and user not in cmdline
        assert len(key) == 64 and len(password) >= 32
        seen = asyncio.run(stranger(server_url(tmp_path / "run"), user, password, "run", key))
        out, err = run.communicate(timeout=120)
    finally:
        run.kill()
    assert run.returncode == 0, err
    assert "Authorization Violation" in seen["anonymous"] or "authorization" in seen["anonymous"].lower(), seen
    assert seen["answers"] == 0, "no forged request was answered"

    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["status"] == "completed" and status["steps_done"] == 120
    sec = status["security"]
    # slow-0: two forged steps, the replay, the stop, the teardown (and the key holder's
    # step past the end and teardown without reply); count-0: the frame moved to its
    # subject and the stop.
    assert sec["rejected_by_workers"] == {"slow-0": 7, "count-0": 2}, sec
    assert sec["rejected"] == 9 and sec["rejected_by_core"] == 0, sec
    slow_log = (tmp_path / "run" / "workers" / "slow-0.log").read_text()
    assert slow_log.count("security: refused") == 7, slow_log
    assert slow_log.count("caviar.run.slow.step fails authentication") == 2, slow_log
    assert "unauthenticated message on caviar.run.stop" in slow_log, slow_log
    assert "unauthenticated message on caviar.run.slow.slow-0.teardown" in slow_log, slow_log
    assert "already used (a replayed message)" in slow_log, slow_log
    assert "step 1000000 is past the end of the episode" in slow_log, slow_log
    assert "teardown without a reply subject" in slow_log, slow_log
    count_log = (tmp_path / "run" / "workers" / "count-0.log").read_text()
    assert count_log.count("security: refused") == 2, count_log
    assert "caviar.run.count.step fails authentication" in count_log, count_log
    assert "worker slow-0 refused" in err, err

    # The recorded messages are those of the same run without a stranger.
    cli("run", "exp.toml", "-q", "--out", "clean", check=0)
    assert json.loads((tmp_path / "clean" / "run.json").read_text())["security"]["rejected"] == 0
    a, b = caviar.load_run(tmp_path / "clean").messages, caviar.load_run(tmp_path / "run").messages
    assert b.height == a.height == 240
    assert b.equals(a)


def test_a_clean_run_records_no_refusals_and_workers_need_the_key(tmp_path, cli):
    write_config(tmp_path, CONFIG.replace("steps = 120", "steps = 10"))
    cli("run", "exp.toml", "-q", "--out", "run", check=0)
    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["security"]["rejected"] == 0, status["security"]
    # Without the run key a worker does not start.
    e = {k: v for k, v in env().items() if not k.startswith("CAVIAR_RUN_KEY")}
    p = subprocess.run([sys.executable, "-m", "caviar.worker", "--nats", "nats://127.0.0.1:1", "--run", "x",
                        "--module", "m"], env=e, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "no run key" in p.stderr, p.stderr


def test_sign_and_verify_are_the_cores(tmp_path):
    key = os.urandom(32).hex()
    sealed = _core.sign(key, "r", "caviar.r.m.step", 5, b"body")
    assert len(sealed) == 4 + 40
    assert _core.verify(key, "r", "caviar.r.m.step", sealed) == (5, b"body")
    for run, subject in [("r", "caviar.r.other.step"), ("r2", "caviar.r.m.step")]:
        with pytest.raises(ValueError, match="fails authentication"):
            _core.verify(key, run, subject, sealed)
    g = _core.Guard("r", key)
    assert g.open("caviar.r.m.step", sealed) == b"body"
    with pytest.raises(ValueError, match="replayed"):
        g.open("caviar.r.m.step", sealed)
    g.schedule(1, 0, 10, 1, True)
    g.accept_step(0, 0)
    with pytest.raises(ValueError, match="not the next step"):
        g.accept_step(2, 0)
    assert g.rejected == 2
    t0 = time.perf_counter()
    frame = os.urandom(1 << 20)
    for i in range(20):
        _core.verify(key, "r", "s", _core.sign(key, "r", "s", i, frame))
    per_mib = (time.perf_counter() - t0) / 20
    assert per_mib < 0.05, f"sealing and checking 1 MiB took {per_mib * 1e3:.1f} ms"
