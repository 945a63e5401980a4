"""Runs that die or hang (issue #13): the run record tells the truth."""

import json
import os
import pathlib
import signal
import subprocess
import time

import pytest

import caviar
from configs import caviar_core, caviar_env, ended_in, episode, module
from conftest import write_config

DYING = (episode(0.1, ["a", "b"], steps=1000) + module("counter", "a", "sample_plugins:Counter")
         + module("exiter", "b", "sample_plugins:Exits", {"at_step": 5}))


def test_a_plugin_that_ends_the_process_is_reported_at_once(tmp_path, cli):
    """os._exit in a plugin: the supervising command says at once what ended the run,
    where, and closes run.json as failed with it; the finished steps stay readable."""
    write_config(tmp_path, DYING)
    p = cli("run", "exp.toml", "-q", "--out", "run")
    assert p.returncode == 1, p.stderr
    assert "the run ended abnormally: the process exited with status 3 without closing the run" in p.stderr
    assert "in module 'exiter' at step 5" in p.stderr and "Traceback" not in p.stderr, p.stderr
    log = caviar.load_run(tmp_path / "run")
    s = log.status
    assert s["status"] == "failed" and s["end_reason"] == "error" and s["steps_done"] == 5, s
    assert s["error"]["module"] == "exiter" and s["error"]["step"] == 5 and "status 3" in s["error"]["message"], s
    assert "pid" not in json.loads((tmp_path / "run" / "run.json").read_text())
    assert log.topic("count")["step"].to_list() == [0, 1, 2, 3, 4]  # step 5's parts were never written
    text = cli("inspect", "run", check=0).stdout
    assert "(failed)" in text and "in module 'exiter', step at step 5" in text, text


def test_a_segfault_in_native_code_is_reported_at_once(tmp_path, cli):
    write_config(tmp_path, DYING.replace("params = { at_step = 5 }", "params = { at_step = 3, segfault = true }"))
    p = cli("run", "exp.toml", "-q", "--out", "run")
    assert p.returncode == 1, p.stderr
    assert "crashed with a segmentation fault (SIGSEGV), in module 'exiter' at step 3" in p.stderr, p.stderr
    assert caviar.load_run(tmp_path / "run").status["status"] == "failed"


@pytest.mark.parametrize("fault, says", [("at_step = 3", "exited (exit status: 3)"),
                                         ("at_step = 3, segfault = true", "exited (signal: 11 (SIGSEGV))")])
def test_over_nats_a_dying_worker_is_reported_as_in_process(tmp_path, cli, fault, says):
    """The same run over NATS: the error names module, step and how the worker ended, then its
    log's last lines or that the log is empty (never a bare "last lines of …:"); steps_done
    is the steps that finished, 3, as in process and as for an exception."""
    write_config(tmp_path, DYING.replace("params = { at_step = 5 }", f"params = {{ {fault} }}")
                 .replace("[modules.counter]", '[transport]\nkind = "nats"\n[modules.counter]'))
    p = cli("run", "exp.toml", "-q", "--out", "run")
    assert p.returncode == 1, p.stderr
    first = next(line for line in p.stderr.splitlines() if line.startswith("error: "))
    assert first.startswith("error: module 'exiter' failed at step 3") and says in first, p.stderr
    assert not first.endswith(":") and ("is empty" in first or "last lines of" in first), p.stderr
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "failed" and s["steps_done"] == 3 and s["error"]["step"] == 3, s


def test_over_nats_a_silent_worker_is_reported_with_what_it_last_wrote(tmp_path, cli):
    """A worker that stops beating but lives (SIGSTOP, as a native crash handler that runs
    gdb for seconds would hold it): the error names module and step, the silence, and the
    last lines of its log, where it said why."""
    write_config(tmp_path, DYING.replace("params = { at_step = 5 }", "params = { at_step = 3, stall = true }")
                 .replace("[modules.counter]", '[transport]\nkind = "nats"\n[transport.nats]\n'
                          'heartbeat_timeout = 1.0\n[modules.counter]'))
    p = cli("run", "exp.toml", "-q", "--out", "run")
    assert p.returncode == 1, p.stderr
    error = p.stderr[p.stderr.index("error: "):]
    assert error.startswith("error: module 'exiter' failed at step 3") and "(no heartbeat)" in error, p.stderr
    assert "last lines of " in error and "exiter: stalling the whole process at step 3" in error, p.stderr


def test_out_of_memory_is_named_when_the_kernel_counted_an_oom_kill():
    """The kernel's OOM killer cannot be provoked safely in a test: the words for it are
    checked against the cgroup counter the parent reads before and after."""
    from caviar.supervise import cause

    assert "out of memory" in cause(-signal.SIGKILL, 4, 5)
    assert cause(-signal.SIGKILL, 4, 4) == "was killed (SIGKILL)"
    assert cause(-signal.SIGKILL, None, None) == "was killed (SIGKILL)"
    assert "status 7" in cause(7, None, None)


def test_unsupervised_a_plugin_that_ends_the_process_leaves_an_abandoned_run(tmp_path, monkeypatch):
    """The engine's own record, without the supervising parent (CAVIAR_SUPERVISED=1): the
    dead process leaves run.json running, and readers call the run abandoned."""
    write_config(tmp_path, DYING)
    p = subprocess.run([caviar_core(), "run", "exp.toml", "-q", "--out", "run"], cwd=tmp_path,
                       env=caviar_env(CAVIAR_SUPERVISED="1"), capture_output=True, text=True, timeout=120)
    assert p.returncode == 3, p.stderr
    raw = json.loads((tmp_path / "run" / "run.json").read_text())
    assert raw["status"] == "running" and raw["pid"] > 0  # what the dead process left
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "abandoned", s
    assert s["steps_done"] == 5 and s["last_step"] == 5 and s["last_modules"] == ["exiter"], s
    assert s["last_stage"] == "b"
    assert "after step 4 (5 steps done)" in s["abandoned"] and "'exiter', at step 5" in s["abandoned"]


def test_kill_9_of_the_core_leaves_an_abandoned_run(tmp_path, cli):
    write_config(tmp_path, DYING.replace("sample_plugins:Exits", "sample_plugins:Slow")
                 .replace("params = { at_step = 5 }", "params = { seconds = 0.02 }"))
    proc = subprocess.Popen([caviar_core(), "run", "exp.toml", "-q", "--out", "run"], cwd=tmp_path, env=caviar_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    parts = tmp_path / "run" / "messages"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list(parts.glob("*.parquet"))) < 20:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # the command; the engine's process dies with it
    proc.wait(timeout=10)
    deadline = time.monotonic() + 10
    while (s := caviar.load_run(tmp_path / "run").status)["status"] == "running" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert s["status"] == "abandoned", s
    done = len(list(parts.glob("part-*.parquet")))
    # A step's part is written before its progress: a kill between the two leaves the
    # status one step behind the parts, never ahead.
    assert done >= 20 and s["steps_done"] in (done, done - 1), (s, done)
    assert s["last_step"] == s["steps_done"] and s["last_modules"] in (["counter"], ["exiter"]), s
    assert "abandoned" in cli("inspect", "run", check=0).stdout


def test_a_simulation_dropped_without_close_is_closed(tmp_path):
    cfg = write_config(tmp_path, DYING.replace("at_step = 5", "at_step = 100000"))
    sim = caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    for _ in range(3):
        sim.step()
    assert caviar.load_run(tmp_path / "run").status["status"] == "running"  # this process lives
    del sim
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "completed" and s["end_reason"] == "closed" and s["steps_done"] == 3, s


def test_a_step_that_never_ends_is_stopped_by_the_watchdog(tmp_path, cli):
    write_config(tmp_path, DYING.replace("at_step = 5", "at_step = 5, hang = true")
                 .replace("steps = 1000", "steps = 1000\nstep_timeout = 1.0"))
    t0 = time.monotonic()
    p = cli("run", "exp.toml", "-q", "--out", "run")
    took = time.monotonic() - t0
    assert p.returncode == 1, p.stderr
    assert "module 'exiter' did not finish step 5 within 1 s (episode.step_timeout)" in p.stderr
    assert "Traceback" not in p.stderr
    log = caviar.load_run(tmp_path / "run")
    s = log.status
    assert s["status"] == "failed" and s["steps_done"] == 5 and s["end_reason"] == "error", s
    assert s["error"]["module"] == "exiter" and s["error"]["step"] == 5, s
    assert log.topic("count")["step"].to_list() == [0, 1, 2, 3, 4]  # finished steps readable
    assert took < 10, took
    print(f"watchdog: run stopped {took:.2f} s after start (step_timeout 1 s)")



@pytest.mark.parametrize("phase", ["setup", "teardown"])
def test_a_setup_or_teardown_that_never_ends_is_stopped_by_the_watchdog(tmp_path, cli, phase):
    """The watchdog covers a module's setup and teardown too (episode.setup_timeout)."""
    write_config(tmp_path, DYING.replace("at_step = 5", f'at_step = 99999, hang_in = "{phase}"')
                 .replace("steps = 1000", "steps = 3\nsetup_timeout = 1.0"))
    t0 = time.monotonic()
    p = cli("run", "exp.toml", "-q", "--out", "run")
    took = time.monotonic() - t0
    assert p.returncode == 1, p.stderr
    assert f"module 'exiter' did not finish {phase} within 1 s (episode.setup_timeout)" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    log = caviar.load_run(tmp_path / "run")
    s = log.status
    assert s["status"] == "failed" and s["end_reason"] == "error", s
    assert s["error"]["module"] == "exiter" and s["error"]["phase"] == phase and s["error"]["step"] is None, s
    # Teardown comes after every step: those steps are recorded and readable.
    assert s["steps_done"] == (3 if phase == "teardown" else 0), s
    assert log.topic("count")["step"].to_list() == ([0, 1, 2] if phase == "teardown" else [])
    assert took < 20, took


# --- Ctrl-C and deadlines (D1-D4) ------------------------------------------------------------
SLOW_IN_PROCESS = (episode(0.1, ["a", "b"], steps=100000)
                   + module("slow", "a", "sample_plugins:Slow", {"seconds": 0.02})
                   + module("count", "b", "sample_plugins:Counter"))

NATS_SLOW = SLOW_IN_PROCESS.replace("[modules.slow]", '[transport]\nkind = "nats"\n[modules.slow]').replace(
    "seconds = 0.02", "seconds = 60.0")


def _start(tmp_path, out):
    return subprocess.Popen([caviar_core(), "run", "exp.toml", "-q", "--out", out], cwd=tmp_path, env=caviar_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(proc, cond, what, timeout=60):
    deadline = time.monotonic() + timeout
    while not cond():
        assert proc.poll() is None, (what, proc.communicate())
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def _started(run_dir, module):
    def cond():
        try:
            return module in json.loads((run_dir / "progress.json").read_text().strip())["modules"]
        except (OSError, ValueError, KeyError):
            return False
    return cond


def test_ctrl_c_in_process_is_an_interruption_never_a_module_crash(tmp_path):
    write_config(tmp_path, SLOW_IN_PROCESS)
    for i in range(5):  # the signal lands inside the plugin's sleep most of the time
        proc = _start(tmp_path, f"run{i}")
        parts = tmp_path / f"run{i}" / "messages"
        _wait_for(proc, lambda p=parts, n=3 + i: p.exists() and len(list(p.glob("*.parquet"))) >= n, "steps")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        s = caviar.load_run(tmp_path / f"run{i}").status
        assert s["status"] == "interrupted" and s["end_reason"] == "interrupted", s


def test_ctrl_c_stops_a_nats_run_waiting_for_a_step_at_once(tmp_path):
    write_config(tmp_path, NATS_SLOW)
    proc = _start(tmp_path, "run")
    try:
        _wait_for(proc, _started(tmp_path / "run", "slow"), "step 0 of 'slow' started")
        time.sleep(0.3)
        err, took = ended_in(proc, 60, signal.SIGINT)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert caviar.load_run(tmp_path / "run").status["status"] == "interrupted"
    print(f"NATS Ctrl-C: process ended {took:.2f} s after SIGINT")
    assert took < 4, took


def test_a_nats_step_past_its_deadline_ends_the_run_at_once(tmp_path):
    write_config(tmp_path, NATS_SLOW.replace("steps = 100000", "steps = 100000\nstep_timeout = 1.0"))
    proc = _start(tmp_path, "run")
    try:
        _wait_for(proc, _started(tmp_path / "run", "slow"), "step 0 of 'slow' started")
        err, took = ended_in(proc, 90)
    finally:
        proc.kill()
    assert proc.returncode == 1, err
    assert "module 'slow' failed at step 0" in err and "no reply within 1 s" in err, err
    print(f"NATS step_timeout 1 s: process ended {took:.2f} s after the step started")
    assert took < 5, took


def test_a_nats_config_error_creates_no_run_directory(tmp_path, cli):
    write_config(tmp_path, NATS_SLOW.replace("seconds = 60.0", 'seconds = "slow"'))
    p = cli("run", "exp.toml", "-q", "--out", "run", check=2)
    assert "modules.slow.params.seconds" in p.stderr, p.stderr
    assert not (tmp_path / "run").exists()
    cli("run", "exp.toml", "-q", check=2)
    assert not (tmp_path / "runs" / "exp-001").exists()


def test_ctrl_c_twice_stops_an_in_process_step_that_takes_long(tmp_path):
    write_config(tmp_path, SLOW_IN_PROCESS.replace("seconds = 0.02", "seconds = 60.0"))
    proc = _start(tmp_path, "run")
    try:
        _wait_for(proc, _started(tmp_path / "run", "slow"), "step 0 of 'slow' started")
        proc.send_signal(signal.SIGINT)
        time.sleep(0.3)
        err, took = ended_in(proc, 30, signal.SIGINT)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "Ctrl-C again to stop at once" in err and "Traceback" not in err, err
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "interrupted" and s["last_modules"] == ["slow"], s
    assert took < 2, took


# --- Python API (D12) ----------------------------------------------------------------------------
def test_python_api_mistakes_are_named(tmp_path):
    cfg = write_config(tmp_path, DYING.replace("at_step = 5", "at_step = 100000"))
    with pytest.raises(TypeError, match="got the string 'episode.steps=5' \\(put it in a list\\)"):
        caviar.Simulation.from_toml(cfg, overrides="episode.steps=5")
    with caviar.Simulation.from_toml(cfg, overrides=["episode.steps=3"], out=tmp_path / "run") as sim:
        sim.run()
    log = caviar.load_run(tmp_path / "run")
    with pytest.raises(ValueError, match="a..b"):
        log.topic("a..b")
    log.messages = log.messages.clear()  # as a run that recorded nothing
    with pytest.raises(ValueError, match="a..b"):
        log.topic("a..b")
    (tmp_path / "run" / "messages.parquet").write_bytes(b"PAR1 not really")
    with pytest.raises(ValueError, match="messages.parquet: not a readable Parquet file"):
        caviar.load_run(tmp_path / "run")
    (tmp_path / "run" / "run.json").write_text("{ half")
    with pytest.raises(ValueError, match="run.json"):
        caviar.load_run(tmp_path / "run")


# --- the NATS server (D5, stale files) ----------------------------------------------------------
def _children(pid: int, name: str) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=,comm=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines() if name in line]


def test_a_dead_nats_server_is_named_at_once_and_leaves_no_files(tmp_path):
    import tempfile

    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = pathlib.Path(tempfile.gettempdir()) / f"caviar-nats-{dead.pid}-4222.conf"
    stale.write_text("listen: 127.0.0.1:4222\n")
    write_config(tmp_path, NATS_SLOW.replace("seconds = 60.0", "seconds = 0.05"))
    proc = _start(tmp_path, "run")
    try:
        parts = tmp_path / "run" / "messages"
        _wait_for(proc, lambda: parts.exists() and len(list(parts.glob("*.parquet"))) >= 3, "steps")
        assert not stale.exists(), "a stale configuration of a dead run is removed"
        engine = json.loads((tmp_path / "run" / "run.json").read_text())["pid"]  # under the supervising command
        own = list(pathlib.Path(tempfile.gettempdir()).glob(f"caviar-nats-{engine}-*.conf"))
        assert own == [], "the server has read its configuration: nothing is left for a kill -9"
        (server,) = _children(engine, "nats-server")
        os.kill(server, signal.SIGKILL)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        proc.kill()
    assert proc.returncode == 1, err
    assert f"the nats-server this run started (pid {server}" in err and "exited" in err, err
    print(f"dead nats-server: run ended {took:.2f} s after kill -9 of the server")
    assert took < 5, took
