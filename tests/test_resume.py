"""Checkpoints and `caviar-core run --resume` (issue #28): a run killed with SIGKILL at a
random step and resumed records exactly the messages of an uninterrupted run with the
same seed; what cannot be resumed is refused, naming why."""

from __future__ import annotations

import json
import pathlib
import random
import signal
import subprocess
import time

import pytest

import caviar
from configs import caviar_core, caviar_env, episode, module, output
from conftest import ROOT, write_config

RESUMABLE = (episode(0.1, ["a", "b"], steps=160, seed=5) + output(checkpoint_every=20)
             + module("count", "a", "sample_plugins:Counter") + module("noise", "a", "sample_plugins:Noise")
             # state, an inbox carried across steps and a random stream:
             + module("tally", "a", "sample_plugins:Tally", subscribe=["count"])
             + module("slow", "b", "sample_plugins:Slow", {"seconds": 0.01}))


def _progress(run_dir: pathlib.Path) -> int:
    try:
        return int(json.loads((run_dir / "progress.json").read_text().strip())["step"])
    except (OSError, ValueError, KeyError):
        return -1


def _kill_at(args: list[str], run_dir: pathlib.Path, step: int, cwd: pathlib.Path) -> None:
    """Starts `caviar-core run ARGS` and kills it (SIGKILL, the supervising process and
    with it the run) once step `step` started."""
    proc = subprocess.Popen([caviar_core(), "run", *args, "-q", "--out", str(run_dir)], cwd=cwd, env=caviar_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while _progress(run_dir) < step:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    time.sleep(0.3)  # the run process dies with its parent (PDEATHSIG)


def _messages(run_dir: pathlib.Path):
    # seq is the order within a step; compared through the row order itself.
    return caviar.load_run(run_dir).messages.drop("seq")


@pytest.mark.parametrize("seed", [1, 2])
def test_a_run_killed_at_a_random_step_resumes_to_the_same_messages(tmp_path, cli, seed):
    write_config(tmp_path, RESUMABLE)
    cli("run", "exp.toml", "-q", "--out", "reference", check=0)
    kill = random.Random(seed).randrange(25, 150)
    _kill_at(["exp.toml"], tmp_path / "run", kill, tmp_path)
    assert caviar.load_run(tmp_path / "run").status["status"] in ("abandoned", "failed")
    before = cli("inspect", "run", check=0).stdout
    assert "resume    from step " in before and "caviar-core run --resume run" in before, before
    p = cli("run", "--resume", "run", "-q", check=0)
    cp = (kill // 20) * 20  # the last checkpoint before the kill (or the kill step's own)
    assert "resumed at step" in p.stderr, p.stderr
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "completed" and s["steps_done"] == 160, s
    assert len(s["resumed_at"]) == 1 and cp <= s["resumed_at"][0] <= kill + 1, (s["resumed_at"], kill)
    after = cli("inspect", "run", check=0).stdout
    assert f"resumed   at step {s['resumed_at'][0]}" in after and "resume    from" not in after, after
    ref, got = _messages(tmp_path / "reference"), _messages(tmp_path / "run")
    assert got.height == ref.height == 160 * 5
    assert got.equals(ref)  # every message, bit for bit, in the same order


def test_the_quickstart_resumes_to_the_same_messages_and_report(tmp_path, cli):
    """The built-in plugins of the quickstart (flight, free-space link, monitor) resume."""
    quick = ROOT / "blueprints" / "quickstart" / "config.toml"
    sets = ["--set", "output.checkpoint_every=30", "--set", "modules.uav.params.speed=20"]
    cli("run", quick, *sets, "-q", "--out", tmp_path / "reference", check=0)
    _kill_at([str(quick), *sets], tmp_path / "run", 40, tmp_path)
    cli("run", "--resume", tmp_path / "run", "-q", check=0)
    ref, got = _messages(tmp_path / "reference"), _messages(tmp_path / "run")
    assert got.equals(ref) and got.height > 100
    report = "artifacts/monitor/throughput.csv"
    assert (tmp_path / "run" / report).read_text() == (tmp_path / "reference" / report).read_text()


def test_a_module_without_state_hooks_makes_resume_refuse_naming_it(tmp_path, cli):
    write_config(tmp_path, RESUMABLE + module("echo", "b", "sample_plugins:Echo"))
    _kill_at(["exp.toml"], tmp_path / "run", 30, tmp_path)
    why = "plugin sample_plugins.Echo has no state()/restore() hooks and does not declare stateless = True"
    p = cli("run", "--resume", "run", check=2)
    assert f"cannot resume: module 'echo': {why}" in p.stderr, p.stderr
    assert f"resume    not possible: module 'echo': {why}" in cli("inspect", "run", check=0).stdout
    # The checkpoint of a run that cannot be resumed names the module and holds nothing else.
    cp = json.loads((tmp_path / "run" / "checkpoint.json").read_text())
    assert [m["name"] for m in cp["modules"]] == ["echo"] and cp["modules"][0]["inbox"] == []
    assert caviar.load_run(tmp_path / "run").status["status"] != "running"


def test_what_cannot_be_resumed_is_refused_saying_why(tmp_path, cli):
    write_config(tmp_path, RESUMABLE.replace("steps = 160", "steps = 6"))
    cli("run", "exp.toml", "-q", "--out", "done", check=0)
    p = cli("run", "--resume", "done", check=2)
    assert "the run completed; there is nothing to resume" in p.stderr
    p = cli("run", "--resume", "nowhere", check=2)
    assert "nowhere" in p.stderr and "Traceback" not in p.stderr
    write_config(tmp_path, RESUMABLE.replace("checkpoint_every = 20", "checkpoint_every = 0"), "none.toml")
    _kill_at(["none.toml"], tmp_path / "none", 10, tmp_path)
    p = cli("run", "--resume", "none", check=2)
    assert "no checkpoint to resume from" in p.stderr and "output.checkpoint_every" in p.stderr
    p = cli("run", "exp.toml", "--resume", "done", check=2)
    assert "cannot be used with" in p.stderr


def test_a_run_over_nats_killed_at_a_random_step_resumes_to_the_same_messages(tmp_path, cli):
    """Over NATS the workers give their plugins' states at each checkpoint; a resumed run
    starts a server and workers again, restores them, and records what an uninterrupted
    run records (here: the in-process one, which records the same)."""
    write_config(tmp_path, RESUMABLE)
    write_config(tmp_path, RESUMABLE.replace("[output]", '[transport]\nkind = "nats"\n[output]'), "nats.toml")
    cli("run", "exp.toml", "-q", "--out", "reference", check=0)
    kill = random.Random(3).randrange(25, 150)
    _kill_at(["nats.toml"], tmp_path / "run", kill, tmp_path)
    p = cli("run", "--resume", "run", "-q", check=0)
    assert "resumed at step" in p.stderr, p.stderr
    s = caviar.load_run(tmp_path / "run").status
    assert s["status"] == "completed" and s["steps_done"] == 160 and len(s["resumed_at"]) == 1, s
    assert _messages(tmp_path / "run").equals(_messages(tmp_path / "reference"))


def test_a_checkpoint_is_due_after_its_wall_time_whatever_the_steps(tmp_path, cli):
    """``output.checkpoint_interval_s`` (60 s by default): a checkpoint once that much wall time
    passed, before ``checkpoint_every`` steps; each step here sleeps longer than the interval, so
    every step but the last writes one, and the run killed anywhere resumes."""
    write_config(tmp_path, RESUMABLE.replace("steps = 160", "steps = 6")
                 .replace("checkpoint_every = 20", "checkpoint_every = 1000\ncheckpoint_interval_s = 0.001"))
    cli("run", "exp.toml", "-q", "--out", "run", check=0)
    assert caviar.load_run(tmp_path / "run").status["checkpoint_step"] == 5
    write_config(tmp_path, RESUMABLE.replace("steps = 160", "steps = 6")
                 .replace("checkpoint_every = 20", "checkpoint_every = 1000\ncheckpoint_interval_s = 0"))
    cli("run", "exp.toml", "-q", "--out", "steps-only", check=0)
    assert caviar.load_run(tmp_path / "steps-only").status.get("checkpoint_step") is None
