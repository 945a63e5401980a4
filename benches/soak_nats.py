"""Soak over NATS (issue #28): 100,000 steps of the quickstart (its UAV slowed so that
the flight outlasts them) with a worker process killed (SIGKILL) at ten random steps.
Runs go back to back: each is planned for the steps still to go and is killed at the
next kill step; the last one runs to its end. Each killed run must end within its
deadline, naming the killed worker's module, with run.json `failed` and every step it
finished readable in the recording; the last must complete.

    .venv/bin/python benches/soak_nats.py                          # 100,000 steps, 10 kills
    .venv/bin/python benches/soak_nats.py --steps 2000 --kills 2   # a quick look

Writes the figures to docs/results/reliability.json ("soak"): runs, steps planned and
run, kills, crashes (a traceback or panic, an exit other than 1), hangs (a run past its
deadline), steps lost (finished but not readable), and the seconds from kill to exit.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import random
import signal
import subprocess
import sys
import tempfile
import time

import caviar

ROOT = pathlib.Path(__file__).resolve().parents[1]
QUICKSTART = ROOT / "blueprints" / "quickstart" / "config.toml"
RESULTS = ROOT / "docs" / "results" / "reliability.json"
# A killed worker is noticed by its exit (the supervisor) or by missed heartbeats (5 s):
# the run must end well within this.
DEADLINE_S = 15.0


def _children(pid: int) -> list[int]:
    """Every descendant of `pid` (from /proc)."""
    parents: dict[int, list[int]] = {}
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        for c in parents.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _workers(pid: int) -> dict[int, str]:
    """The worker processes under `pid`: {pid: module}."""
    found = {}
    for c in _children(pid):
        try:
            argv = pathlib.Path(f"/proc/{c}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"caviar.worker" in argv and b"--module" in argv:
            found[c] = argv[argv.index(b"--module") + 1].decode()
    return found


def _step(run_dir: pathlib.Path) -> int:
    try:
        return int(json.loads((run_dir / "progress.json").read_text().strip())["step"])
    except (OSError, ValueError, KeyError):
        return -1


def soak_run(i: int, steps: int, kill_at: int | None, rng: random.Random, out: pathlib.Path) -> dict:
    """One run of `steps` steps; a random worker killed at step `kill_at` (None: none)."""
    run_dir = out / f"soak-{i:02d}"
    cmd = [str(pathlib.Path(sys.executable).parent / "caviar-core"), "run", str(QUICKSTART), "-q",
           "--out", str(run_dir), "--set", 'transport.kind="nats"', "--set", f"episode.steps={steps}",
           # Slow enough that the flight (which ends the episode) outlasts the planned steps.
           "--set", "modules.uav.params.speed=0.01"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    start = time.monotonic()
    module = None
    if kill_at is not None:
        while _step(run_dir) < kill_at:
            if proc.poll() is not None:
                raise SystemExit(f"run {i} ended before step {kill_at}: {proc.communicate()[1]}")
            time.sleep(0.01)
        workers = _workers(proc.pid)
        victim, module = rng.choice(sorted(workers.items()))
        os.kill(victim, signal.SIGKILL)
    killed = time.monotonic()
    try:
        # The last run, not killed, has as long as its steps take.
        _, err = proc.communicate(timeout=DEADLINE_S if module else None)
        hang = False
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        hang = True
    ended_s = time.monotonic() - killed
    log = caviar.load_run(run_dir)
    status = log.status
    done = int(status["steps_done"])
    recorded = set(log.topic("3D.mobility.positions")["step"].to_list())
    # The step a module failed in counts as done (its earlier stages ran and are
    # recorded, as in-process); every step before it must be recorded whole.
    failed_in = (status.get("error") or {}).get("step")
    finished = set(range(done)) - {failed_in}
    lost = len(finished - recorded)
    if module is None:  # the last run: it completes
        named = status["status"] == "completed" and done == steps
        crash = proc.returncode != 0 or "panicked" in err
    else:
        named = f"'{module}'" in err and (status.get("error") or {}).get("module") == module
        crash = proc.returncode != 1 or "Traceback" in err or "panicked" in err
    row = {"run": i, "kill_at_step": kill_at, "killed_module": module, "exit": proc.returncode,
           "seconds_to_end": round(ended_s, 3), "steps_done": done, "steps_lost": lost,
           "status": status["status"], "error_module": (status.get("error") or {}).get("module"),
           "failed_in_step": failed_in, "named": named, "crash": crash, "hang": hang,
           "wall_s": round(time.monotonic() - start, 1),
           "stderr": err.strip().splitlines()[-3:]}
    what = f"killed '{module}' at step {kill_at}" if module else "not killed"
    print(f"run {i}: {what}: exit {proc.returncode} after {ended_s:.2f} s, {done} of {steps} steps done, "
          f"{lost} lost, {'as expected' if named else 'NOT AS EXPECTED'}", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100_000, help="steps in all")
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--seed", type=int, default=28)
    ap.add_argument("--write", action=argparse.BooleanOptionalAction, default=True,
                    help="write docs/results/reliability.json")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    # Kill steps, at least 200 apart (a run needs a moment to start its workers).
    while True:
        kills = sorted(rng.sample(range(200, args.steps - 200), args.kills))
        if all(b - a >= 200 for a, b in zip(kills, kills[1:], strict=False)):
            break
    rows, done = [], 0
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="caviar-soak-") as tmp:
        for i, at in enumerate([*kills, None]):
            row = soak_run(i, args.steps - done, None if at is None else at - done, rng, pathlib.Path(tmp))
            rows.append(row)
            done += row["steps_done"]
    killed = [r for r in rows if r["killed_module"]]
    summary = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "blueprint": "quickstart over NATS (transport.kind = \"nats\", modules.uav.params.speed = 0.01)",
        "steps_planned": args.steps, "steps_run": done, "runs": len(rows), "kills": len(killed),
        "crashes": sum(r["crash"] for r in rows), "hangs": sum(r["hang"] for r in rows),
        "not_as_expected": sum(not r["named"] for r in rows),
        "steps_lost": sum(r["steps_lost"] for r in rows),
        "seconds_kill_to_end_max": max(r["seconds_to_end"] for r in killed), "deadline_s": DEADLINE_S,
        "wall_s": round(time.monotonic() - t0, 1),
        "rows": rows,
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))
    if args.write:
        data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
        data["soak"] = summary
        RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    failed = summary["crashes"] or summary["hangs"] or summary["not_as_expected"] or summary["steps_lost"]
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
