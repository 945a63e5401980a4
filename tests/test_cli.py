"""The `caviar-core` command line, the quickstart blueprint and replay."""

import json
import math
import shutil

import numpy as np
import pytest

import caviar
from caviar._gpu import open_sampler
from configs import episode, module
from conftest import ROOT, write_config

QUICKSTART = ROOT / "blueprints" / "quickstart" / "config.toml"

CRASHING = (episode(0.1, ["a"], steps=100) + module("alive", "a", "sample_plugins:Counter")
            + module("crash", "a", "sample_plugins:Crash", {"at_step": 7}))


def test_quickstart_runs_and_shows_the_three_paper_topics(tmp_path, cli):
    p = cli("run", QUICKSTART, "--quiet", "--out", "qs", check=0)
    assert "qs: completed" in p.stdout
    log = caviar.load_run(tmp_path / "qs")
    topics = set(log.messages["topic"].unique())
    assert {"3D.mobility.positions", "communications.throughput", "communications.state",
            "caviar.episode.end", "ai.link.report"} <= topics

    pos = log.topic("3D.mobility.positions")
    assert set(pos["UE_type"]) == {"UAV"} and set(pos["UE_Id"]) == {"uav1"}
    xyz = np.array([[p["x"], p["y"], p["z"]] for p in pos["position"].to_list()])
    # 5 m/s at Ts = 0.1 s: 0.5 m of path per step until the last waypoint.
    ned = np.loadtxt(ROOT / "plugins" / "caviar_plugins" / "data" / "central_park_path0.csv", delimiter=",",
                     skiprows=1)
    length = np.linalg.norm(np.diff(ned, axis=0), axis=1).sum()
    assert len(pos) == math.ceil(length / 0.5) + 1
    hops = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    assert np.all(hops <= 0.5 + 1e-9)
    assert np.sum(np.isclose(hops, 0.5)) >= len(hops) - len(ned)  # shorter only across corners
    # First position: the first waypoint mapped from AirSim NED to the scene frame.
    assert np.allclose(xyz[0], [23.34 - 320.34, -3.42 + 206.58, 137.23 - 128])

    # Throughput against an independent link budget computation.
    thr = log.topic("communications.throughput")
    assert thr["step"].to_list() == pos["step"].to_list()
    d = np.linalg.norm(xyz - np.array([-154.0, 64.0, 120.0]), axis=1)
    lam = 299_792_458.0 / 40e9
    gain_db = 20 * np.log10(lam / (4 * math.pi * d)) + 10 * np.log10(64 * 4)
    noise_dbw = 10 * np.log10(1.380649e-23 * (290 + 298.15) * 40e6)
    sinr_db = 10 * np.log10(0.5) + gain_db - 10 * np.log10(10 ** (noise_dbw / 10) + 10 ** (-130 / 10))
    expected_mbps = 40 * np.log2(1 + 10 ** (sinr_db / 10))
    assert np.allclose(thr["throughput"].to_numpy(), expected_mbps, rtol=1e-9)
    assert log.topic("communications.state")["value"].to_list() == ["Ready"] * len(pos)

    # The episode ended at the last waypoint, and the monitor wrote its plot.
    assert log.status["status"] == "completed" and log.status["steps_planned"] is None
    assert (tmp_path / "qs" / "artifacts" / "monitor" / "throughput.png").stat().st_size > 10_000

    text = cli("inspect", "qs", check=0).stdout
    assert "communications.throughput" in text and "(completed)" in text and "RTF" in text
    for name in ("uav", "comm", "monitor", "caviar.core"):
        assert f"\n{name} " in text


def test_numbered_run_directories_and_overrides(tmp_path, cli):
    shutil.copy(QUICKSTART, tmp_path / "qs.toml")
    cli("run", "qs.toml", "-q", "--set", "episode.steps=5", "--set", "output.name=short", check=0)
    cli("run", "qs.toml", "-q", "--set", "episode.steps=7", "--set", "output.name=short", check=0)
    a, b = caviar.load_run(tmp_path / "runs" / "short-001"), caviar.load_run(tmp_path / "runs" / "short-002")
    assert (a.status["steps_done"], b.status["steps_done"]) == (5, 7)
    assert "steps = 7" in b.config_text  # the exact configuration of the run is kept
    assert b.status["overrides"] == ["episode.steps=7", "output.name=short"]


def test_validate_says_what_the_wiring_lets_run_at_once(cli):
    """The SAR loop is closed (the mission's decision of step k moves the UAV of step k+1):
    nothing of step k+1 may start before step k ends, and within a step only modules no data
    path joins could share a stage. The quickstart's flight of step k+1 depends on nothing
    its link computes."""
    sar = cli("validate", str(ROOT / "blueprints/sar/config.toml"), check=0).stdout
    assert "within a step, no data path between (they could share a stage): camera and beams; camera and comm" in sar
    assert "across steps: nothing could overlap; step k+1 waits for step k, e.g. mission ('mission.hover') → uav @k+1" \
        in sar
    quick = cli("validate", str(QUICKSTART), check=0).stdout
    assert "within a step: each module depends on every earlier stage" in quick
    assert "across steps, could overlap: uav of step k+1 during comm of step k;" in quick


def test_validate_reports_errors_without_running(tmp_path, cli):
    good = write_config(tmp_path, CRASHING)
    assert "ok (2 modules in 1 stages, Ts = 0.1 s, 100 steps)" in cli("validate", good, check=0).stdout
    bad = write_config(tmp_path, CRASHING.replace("steps = 100", "steps = -3"), "bad.toml")
    p = cli("validate", bad, check=2)
    assert "bad.toml:3: episode.steps: invalid value: integer `-3`" in p.stderr
    p = cli("run", bad, check=2)
    assert "episode.steps" in p.stderr
    assert not (tmp_path / "runs").exists()
    p = cli("run", good, "--set", "modules.alive.params.scale=fast", check=2)
    assert "modules.alive.params.scale: expected float, got str 'fast'" in p.stderr
    p = cli("run", good, "--set", "modules.alive.every=0", check=2)
    assert "modules.alive.every: expected a period of at least 1 step" in p.stderr


def test_a_crashing_plugin_stops_the_cli_with_module_step_and_traceback(tmp_path, cli):
    write_config(tmp_path, CRASHING)
    p = cli("run", "exp.toml", "--quiet", check=1)
    assert "module 'crash' failed at step 7 (t = 0.700 s): ZeroDivisionError: division by zero" in p.stderr
    assert "Traceback (most recent call last)" in p.stderr and "sample_plugins.py" in p.stderr
    log = caviar.load_run(tmp_path / "runs" / "exp-001")
    assert log.status["status"] == "failed" and log.status["steps_done"] == 7  # (steps 0-6 finished)
    assert log.topic("count")["step"].to_list() == list(range(8))  # module 'alive' ran in step 7 too
    assert log.topic("crash.alive")["step"].to_list() == list(range(7))
    assert "failed" in cli("inspect", "runs/exp-001", check=0).stdout


def test_parts_of_an_unfinished_run_are_readable(tmp_path):
    """A killed process leaves per-step parts; the readers take them as they are."""
    sim = caviar.Simulation.from_toml(write_config(tmp_path, CRASHING.replace("at_step = 7", "at_step = 1000")),
                                      out=tmp_path / "run")
    for _ in range(5):
        sim.step()
    parts = sorted((tmp_path / "run" / "messages").glob("part-*.parquet"))
    assert len(parts) == 5  # flushed after every step
    log = caviar.load_run(tmp_path / "run")
    assert log.status["status"] == "running"
    assert log.topic("count")["step"].to_list() == [0, 1, 2, 3, 4]
    assert log.to_pandas()["step"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    sim.close()
    assert (tmp_path / "run" / "messages.parquet").exists() and not (tmp_path / "run" / "messages").exists()
    assert caviar.load_run(tmp_path / "run").status["status"] == "completed"


def test_replay_reproduces_the_throughput_from_recorded_mobility(tmp_path, cli):
    cli("run", QUICKSTART, "-q", "--out", "original", "--set", "episode.steps=40", check=0)
    write_config(tmp_path, episode(0.1, ["mobility", "communications"], steps=40)
                 + module("mobility", "mobility", "caviar.replay", {"run": "original", "topics": ["3D.mobility.>"]})
                 + module("comm", "communications", "free-space-link"), "replay.toml")
    cli("run", "replay.toml", "-q", "--out", "replayed", check=0)
    original, replayed = caviar.load_run(tmp_path / "original"), caviar.load_run(tmp_path / "replayed")
    assert set(replayed.topic("3D.mobility.positions")["source"]) == {"mobility"}
    for topic in ("3D.mobility.positions", "communications.throughput"):
        a = original.topic(topic).drop("source")
        b = replayed.topic(topic).drop("source")
        assert a.equals(b), topic

    write_config(tmp_path, (tmp_path / "replay.toml").read_text().replace('"3D.mobility.>"', '"nothing.here"'),
                 "empty.toml")
    p = cli("run", "empty.toml", check=2)
    assert "modules.mobility.params.topics: no recorded message" in p.stderr


def test_run_json_is_complete(tmp_path, cli):
    cli("run", QUICKSTART, "-q", "--out", "r", "--set", "episode.steps=3", check=0)
    status = json.loads((tmp_path / "r" / "run.json").read_text())
    assert status["status"] == "completed"
    assert status["steps_done"] == 3 and status["ts"] == 0.1
    assert math.isclose(status["virtual_time_s"], 0.3)
    assert status["modules"] == ["uav", "comm", "monitor"]
    assert status["error"] is None
    # The paper's RTF: wall-clock time over virtual time.
    assert status["rtf"] == pytest.approx(status["wall_s"] / status["virtual_time_s"])
    assert status["rtf_definition"].startswith("T_p/T_v")


def test_report_draws_resource_figures_across_runs(tmp_path, cli):
    for n, steps in ((1, 5), (2, 9)):
        cli("run", QUICKSTART, "-q", "--out", f"r{n}", "--set", f"episode.steps={steps}",
            "--set", f"modules.uav.params.start_m={100 * n}", check=0)
    p = cli("report", "r1", "r2", "--labels", "1", "2", "--xlabel", "UAVs", "--out", "rep", check=0)
    assert "modules.png" in p.stdout
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert report["labels"] == ["1", "2"] and [r["steps"] for r in report["runs"]] == [5, 9]
    for r in report["runs"]:
        assert set(r["modules"]) == {"uav", "comm", "monitor", "caviar.core"}
        assert all(m["max_rss_mib"] > 20 and m["wall_s_per_step"] >= 0 for m in r["modules"].values())
        # GPU columns are filled only where nvidia-ml-py sees a GPU (test_gpu_sampling_* below).
        assert all((m["max_gpu_mem_mib"] is None) == (open_sampler() is None) for m in r["modules"].values()
                   if m is not r["modules"]["caviar.core"])
    for png in ("modules.png", "wall_clock.png"):
        assert (tmp_path / "rep" / png).stat().st_size > 5_000
    first = caviar.load_run(tmp_path / "r2").topic("3D.mobility.positions")["position"].to_list()[0]
    ned = np.loadtxt(ROOT / "plugins" / "caviar_plugins" / "data" / "central_park_path0.csv", delimiter=",",
                     skiprows=1)
    start = np.array([23.34, -3.42, 137.23]) + np.array([1, -1, -1]) * ned[0]
    assert math.dist([first["x"], first["y"], first["z"]], start) > 150  # started 200 m along the route
    assert cli("report", "nothing-here", check=2)


def test_gpu_sampling_follows_what_nvidia_ml_py_sees():
    """With an NVIDIA driver and GPU the sampler reports utilisation and this process's
    GPU memory; without (this development machine), there is no sampler and no numbers."""
    import pynvml

    try:
        pynvml.nvmlInit()
        has_gpu = pynvml.nvmlDeviceGetCount() > 0
    except pynvml.NVMLError:
        has_gpu = False
    sampler = open_sampler()
    assert (sampler is not None) == has_gpu
    if sampler is not None:
        util, mem = sampler.sample()
        assert 0.0 <= util <= 100.0 and mem >= 0.0


STATUS = episode(0.1, ["a"], steps=5) + module("counter", "a", "sample_plugins:Status")


def test_a_modules_status_line_is_shown_with_the_progress_and_recorded(tmp_path, cli):
    write_config(tmp_path, STATUS)
    p = cli("run", "exp.toml", "--out", "st", check=0)  # stderr is a pipe: the log lines
    lines = p.stderr.splitlines()
    assert "step 5/5, t = 0.50 s" in "\n".join(lines) and lines[-1] == "  counter: 5 stepssaid", p.stderr
    assert "counter: 5 stepssaid" in [ln for ln in lines if ln.startswith("step 5/5")][0]
    log = caviar.load_run(tmp_path / "st")
    said = log.topic(caviar.STATUS_TOPIC)
    assert len(said) == 5
    quiet = cli("run", "exp.toml", "--out", "q", "--quiet", check=0)
    assert "counter:" not in quiet.stderr
    # Only caviar.episode.end and caviar.status are open to modules under caviar.
    write_config(tmp_path, STATUS.replace('"sample_plugins:Status"',
                                          '"sample_plugins:Status"\nparams = { bad_at = 2 }'))
    bad = cli("run", "exp.toml", "--out", "bad", check=1)
    assert "reserved for the core" in bad.stderr and "caviar.status" in bad.stderr, bad.stderr


@pytest.mark.parametrize("config", sorted((ROOT / "blueprints").glob("*/*.toml")),
                         ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_shipped_blueprint_validates_without_a_wiring_warning(cli, config):
    """Topics a blueprint records for analysis are declared (``output.analysis``) and a
    plugin's optional inputs (``Plugin.optional``) are not warned about: a shipped blueprint
    says nothing but ok. Wiring mistakes still warn (tests/test_boundary.py)."""
    p = cli("validate", config, check=0)
    assert ": ok (" in p.stdout
    assert "warning" not in p.stderr, p.stderr
