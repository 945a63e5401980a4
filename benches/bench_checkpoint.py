"""What checkpoints cost (issue #28): the quickstart in process, its UAV slowed to make
a long episode, with `output.checkpoint_every` 0 (none), 100 (the default) and 10,
runs interleaved and repeated: the wall time of the steps (run.json's `wall_s`, which
counts the checkpoints) per configuration, its median and the ratio to no checkpoints
(noisy on a busy machine), and the share of it spent writing checkpoints, measured
directly (run.json's `checkpoint_s`).
Written to docs/results/reliability.json ("checkpoint").

With ``--sar``, the main job (the SAR blueprint, ray-traced, every plugin saving its
state) instead: one run checkpointing every 10 steps gives the cost of one checkpoint
(run.json's ``checkpoint_s`` over the checkpoints written) and, in the same run, the
median step time (progress timings); their ratio is the share at the default interval
(100 steps) and at 10. Written to "checkpoint_sar".

    .venv/bin/python benches/bench_checkpoint.py [--steps 3000] [--repeat 5]
    .venv/bin/python benches/bench_checkpoint.py --sar [--steps 60]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
QUICKSTART = ROOT / "blueprints" / "quickstart" / "config.toml"
SAR = ROOT / "blueprints" / "sar" / "config.toml"
RESULTS = ROOT / "docs" / "results" / "reliability.json"


def run_once(out: pathlib.Path, steps: int, every: int) -> tuple[float, float]:
    exe = pathlib.Path(sys.executable).parent / "caviar-core"
    subprocess.run([str(exe), "run", str(QUICKSTART), "-q", "--out", str(out),
                    "--set", f"episode.steps={steps}", "--set", "modules.uav.params.speed=0.01",
                    "--set", f"output.checkpoint_every={every}"], check=True, capture_output=True)
    status = json.loads((out / "run.json").read_text())
    assert status["status"] == "completed" and status["steps_done"] == steps, status
    return float(status["wall_s"]), float(status["checkpoint_s"])


def sar(steps: int, every: int = 10) -> dict:
    """The SAR blueprint checkpointing every ``every`` steps: per checkpoint cost, step time."""
    import polars as pl

    import caviar

    exe = pathlib.Path(sys.executable).parent / "caviar-core"
    with tempfile.TemporaryDirectory(prefix="caviar-cp-sar-") as tmp:
        out = pathlib.Path(tmp) / "sar"
        proc = subprocess.Popen([str(exe), "run", str(SAR), "--out", str(out), "--set", f"episode.steps={steps}",
                                 "--set", f"output.checkpoint_every={every}"], stderr=subprocess.PIPE, text=True)
        _, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"the SAR run failed:\n{err[-3000:]}")
        log = caviar.load_run(out)
        status = log.status
        checkpoint = json.loads((out / "checkpoint.json").read_text())
        # A step's time: its modules' wall times added up (the recorded timings).
        step_s = log.timings.group_by("step").agg(pl.col("wall_s").sum())["wall_s"].to_list()
    written = status["steps_done"] // every
    per_checkpoint = float(status["checkpoint_s"]) / written
    median_step = statistics.median(step_s)
    modules = [m["name"] for m in checkpoint["modules"]]
    return {"machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
            "blueprint": "blueprints/sar/config.toml (defaults: 3e5 samples, UAV body, every plugin saving state)",
            "steps": status["steps_done"], "checkpoint_every": every, "checkpoints_written": written,
            "modules_saved": modules, "checkpoint_ms": 1e3 * per_checkpoint, "median_step_s": median_step,
            "share_pct_every_10": 100 * per_checkpoint / (10 * median_step),
            "share_pct_default_100": 100 * per_checkpoint / (100 * median_step),
            "checkpoint_s": float(status["checkpoint_s"]), "wall_s": float(status["wall_s"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=None, help="3000 (quickstart), 60 (--sar)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--sar", action="store_true", help="the SAR blueprint (see the module docstring)")
    ap.add_argument("--write", action=argparse.BooleanOptionalAction, default=True)
    args = ap.parse_args()
    if args.sar:
        result = sar(args.steps or 60)
        print(json.dumps(result, indent=1))
        if args.write:
            data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
            data["checkpoint_sar"] = result
            RESULTS.write_text(json.dumps(data, indent=1) + "\n")
        return
    args.steps = args.steps or 3000
    intervals = [0, 100, 10]
    walls: dict[int, list[float]] = {k: [] for k in intervals}
    shares: dict[int, list[float]] = {k: [] for k in intervals}
    with tempfile.TemporaryDirectory(prefix="caviar-cp-") as tmp:
        for r in range(args.repeat):
            for every in intervals:
                wall, cp = run_once(pathlib.Path(tmp) / f"r{r}-{every}", args.steps, every)
                walls[every].append(wall)
                shares[every].append(cp / wall)
            print(f"round {r + 1}/{args.repeat}: " + ", ".join(
                f"every {k}: {walls[k][-1]:.3f} s" for k in intervals), flush=True)
    base = statistics.median(walls[0])
    rows = {str(k): {"wall_s_median": statistics.median(v), "ms_per_step": 1e3 * statistics.median(v) / args.steps,
                     "ratio_to_none": statistics.median(v) / base, "wall_s": v,
                     # Measured directly (run.json checkpoint_s), free of run-to-run noise.
                     "checkpoint_share_pct": 100 * statistics.median(shares[k])} for k, v in walls.items()}
    summary = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
               "blueprint": "quickstart in process (modules.uav.params.speed = 0.01)",
               "steps": args.steps, "repeat": args.repeat, "checkpoint_every": rows,
               "default_checkpoint_share_pct": rows["100"]["checkpoint_share_pct"]}
    print(json.dumps({k: v for k, v in summary.items() if k != "checkpoint_every"}, indent=1))
    for k, v in rows.items():
        print(f"checkpoint_every {k:>3}: {v['ms_per_step']:.3f} ms/step, x{v['ratio_to_none']:.3f}, "
              f"checkpoints {v['checkpoint_share_pct']:.2f} % of the wall time")
    if args.write:
        data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
        data["checkpoint"] = summary
        RESULTS.write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
