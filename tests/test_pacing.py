"""Wall-clock pacing (issue #25): ``episode.pace`` keeps step k no earlier than
t0 + k·Ts/pace; late steps are counted, and ``behind`` catches up or drops steps.

The runs are short (about a second each) and their tolerances are stated: a step may
start up to 30 ms after its slot on a busy 2-core machine, and at most one step in ten."""

from __future__ import annotations

import json

import numpy as np
import pytest

import caviar
from configs import caviar_core, caviar_env, ended_in
from conftest import write_config

CONFIG = """
[episode]
ts = {ts}
steps = {steps}
stages = ["s"]
{pacing}

[modules.clock]
stage = "s"
plugin = "sample_plugins:WallClock"
params = {{ seconds = {seconds} }}
"""

TOLERANCE_S = 0.030


def _run(cli, tmp_path, name: str, ts: float, steps: int, pacing: str, seconds: float = 0.0):
    cfg = write_config(tmp_path, CONFIG.format(ts=ts, steps=steps, pacing=pacing, seconds=seconds), f"{name}.toml")
    cli("run", "-q", cfg, "--out", tmp_path / name, check=0)
    status = json.loads((tmp_path / name / "run.json").read_text())
    log = caviar.load_run(tmp_path / name)
    clock = [m.data for m in log.decoded("clock.wall")]
    return status, clock


@pytest.mark.parametrize("pace", [1.0, 2.0])
def test_a_paced_run_keeps_its_steps_on_the_wall_clock(cli, tmp_path, pace):
    ts, steps = 0.05 * pace, 20  # 20 slots of 50 ms of wall clock
    status, clock = _run(cli, tmp_path, f"pace{pace}", ts, steps, f"pace = {pace}")
    wall = np.array([c["wall"] for c in clock])
    assert [c["step"] for c in clock] == list(range(steps))
    # Each step's start against its slot; the plugin's clock starts a few ms after the
    # engine's t0 (the first step's own overhead), so lateness is taken from the earliest.
    offsets = (wall - wall[0]) - np.arange(steps) * ts / pace
    offsets -= offsets.min()
    assert np.mean(offsets > TOLERANCE_S) <= 0.1, offsets
    p = status["pacing"]
    assert p["pace"] == pace and p["behind"] == "catch-up" and p["steps"] == steps
    assert p["dropped_steps"] == 0 and p["late_steps"] <= 2 and p["p99_late_ms"] < 1e3 * TOLERANCE_S * 3, p
    # Faster than real time with pace 2: 20 steps of 0.1 s virtual in about 1 s of wall clock.
    assert wall[-1] - wall[0] == pytest.approx((steps - 1) * ts / pace, abs=0.1)


def test_an_unpaced_run_races_ahead_and_reports_no_pacing(cli, tmp_path):
    status, clock = _run(cli, tmp_path, "free", 1.0, 10, "")
    wall = np.array([c["wall"] for c in clock])
    assert wall[-1] - wall[0] < 2.0  # 9 s of virtual time
    assert "pacing" not in status


def test_catch_up_runs_every_late_step_and_reports_the_lateness(cli, tmp_path):
    """Each step takes 80 ms of 50 ms slots: every step after the first is late, by
    30 ms more each time; none is lost, and run.json and inspect say how late."""
    status, clock = _run(cli, tmp_path, "heavy", 0.05, 10, 'pace = 1.0\nbehind = "catch-up"', seconds=0.08)
    assert [c["step"] for c in clock] == list(range(10))
    p = status["pacing"]
    assert p["late_steps"] == 9 and p["dropped_steps"] == 0, p
    # Step k starts about k·30 ms late: the last, 270 ms.
    assert 250 <= p["worst_late_ms"] <= 270 + 1e3 * TOLERANCE_S * 3, p
    assert p["p99_late_ms"] == pytest.approx(p["worst_late_ms"]), p
    late = np.array([c["wall"] for c in clock]) - clock[0]["wall"] - np.arange(10) * 0.05
    assert late[-1] * 1e3 == pytest.approx(p["worst_late_ms"], abs=5.0)


def test_drop_skips_the_steps_whose_slot_passed_and_counts_them(cli, tmp_path):
    """Each step takes 130 ms of 50 ms slots: after each step two slots have passed, so
    about two steps in three are dropped; virtual time goes on, the last step runs."""
    status, clock = _run(cli, tmp_path, "drop", 0.05, 30, 'pace = 1.0\nbehind = "drop"', seconds=0.13)
    steps = [c["step"] for c in clock]
    assert steps[0] == 0 and steps[-1] == 29 and steps == sorted(set(steps))
    p = status["pacing"]
    assert p["dropped_steps"] == 30 - len(steps) and p["steps"] == len(steps), (p, steps)
    assert 15 <= p["dropped_steps"] <= 22, p
    # Each step that ran started within its own slot: late by less than one slot (plus the
    # stated jitter). Not the last: near the end there may be fewer steps left than slots
    # passed, and the last step then runs, late from its own slot by up to a step's time.
    wall = np.array([c["wall"] for c in clock])
    late = (wall - wall[0]) - np.array(steps) * 0.05
    late -= late.min()
    assert np.all(late[:-1] < 0.05 + TOLERANCE_S), late
    assert p["worst_late_ms"] < 1e3 * (0.13 + 0.05 + TOLERANCE_S), p
    times = [c["t"] for c in clock]
    assert times == pytest.approx([s * 0.05 for s in steps])
    assert status["steps_done"] == 30 and status["status"] == "completed"


def test_inspect_shows_the_pacing(cli, tmp_path):
    _run(cli, tmp_path, "shown", 0.05, 4, 'pace = 1.0\nbehind = "drop"', seconds=0.0)
    out = cli("inspect", tmp_path / "shown", check=0).stdout
    line = next(x for x in out.splitlines() if x.startswith("pacing"))
    assert "pace 1.0 (real time)" in line and "of 4 steps late" in line and "dropped (drop)" in line, line


@pytest.mark.parametrize("pacing, key, expected", [
    ("pace = 0.0", "episode.pace", "expected a positive factor of real time"),
    ("pace = -2.0", "episode.pace", "expected a positive factor of real time"),
    ('pace = 1.0\nbehind = "later"', "episode.behind", 'expected one of ["catch-up", "drop"]'),
    ('behind = "drop"', "episode.behind", "only a paced run"),
])
def test_bad_pacing_names_the_key_and_line(cli, tmp_path, pacing, key, expected):
    text = CONFIG.format(ts=0.1, steps=2, pacing=pacing, seconds=0.0)
    cfg = write_config(tmp_path, text)
    p = cli("run", cfg, check=2)
    line = text[:text.index(pacing.splitlines()[-1])].count("\n") + 1
    assert f"{cfg}:{line}: {key}: {expected}" in p.stderr, p.stderr
    assert not (tmp_path / "runs").exists()


def test_ctrl_c_ends_a_paced_run_waiting_for_its_next_slot(tmp_path):
    """Steps every 5 s of wall clock: a Ctrl-C while the run waits for its next slot ends
    it at once, as an interruption, with what was recorded readable."""
    import signal
    import subprocess
    import time

    cfg = write_config(tmp_path, CONFIG.format(ts=5.0, steps=10, pacing="pace = 1.0", seconds=0.0))
    proc = subprocess.Popen([caviar_core(), "run", "-q", str(cfg), "--out", str(tmp_path / "run")], env=caviar_env(),
                            stderr=subprocess.PIPE, text=True)
    try:
        parts, deadline = tmp_path / "run" / "messages", time.monotonic() + 60
        while not (parts.exists() and any(parts.glob("*.parquet"))):  # step 0 recorded
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.5)  # the run now waits about 4.5 s for step 1's slot
        err, took = ended_in(proc, 30, signal.SIGINT)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert took < 2.0, took
    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["status"] == "interrupted" and status["steps_done"] <= 2, status
    assert [c["step"] for c in (m.data for m in caviar.load_run(tmp_path / "run").decoded("clock.wall"))][0] == 0
