"""Barrier latency of the engine with Python plugins, against an asyncio barrier
measured in the same run.

    .venv/bin/python benches/bench_core.py [--steps 2000] [--out bench-results/core.json]

Writes JSON and prints a markdown table. The Rust-side figures come from
`cargo bench --bench router` (criterion).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import pathlib
import platform
import statistics
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import caviar  # noqa: E402


def asyncio_barrier_us(tasks: int, rounds: int) -> float:
    """Mean time of one round in which `tasks` asyncio tasks are released and all report back."""

    async def main() -> float:
        go = [asyncio.Event() for _ in range(tasks)]
        done = asyncio.Queue()

        async def worker(i):
            while True:
                await go[i].wait()
                go[i].clear()
                done.put_nowait(i)

        workers = [asyncio.create_task(worker(i)) for i in range(tasks)]
        t0 = time.perf_counter()
        for _ in range(rounds):
            for e in go:
                e.set()
            for _ in range(tasks):
                await done.get()
        elapsed = time.perf_counter() - t0
        for w in workers:
            w.cancel()
        return elapsed / rounds * 1e6

    return asyncio.run(main())


def config(modules: int, plugin: str) -> str:
    text = '[episode]\nts = 0.1\nstages = ["s"]\n[output]\nflush_interval = 3600.0\n'
    for i in range(modules):
        text += f'[modules.m{i}]\nstage = "s"\nplugin = "bench_plugins:{plugin}"\n'
    return text


def step_us(path: pathlib.Path, steps: int, tmp: pathlib.Path, warm_up: int = 20) -> float:
    """Mean wall time of one engine step of the experiment at `path`, in µs."""
    sim = caviar.Simulation.from_toml(path, out=tempfile.mkdtemp(dir=tmp))
    for _ in range(warm_up):
        sim.step()
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step()
    elapsed = time.perf_counter() - t0
    sim.close()
    return elapsed / steps * 1e6


def caviar_step_us(modules: int, plugin: str, steps: int, tmp: pathlib.Path) -> float:
    path = tmp / f"{plugin}-{modules}.toml"
    path.write_text(config(modules, plugin))
    return step_us(path, steps, tmp)


def repeat(fn, n=5):
    """Median of n repetitions (the machine is noisy)."""
    return statistics.median(fn() for _ in range(n))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--out", default="bench-results/core.json")
    args = ap.parse_args()

    results = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                           "python": platform.python_version(), "caviar": caviar.__version__},
               "baseline": {}, "caviar": []}
    base = repeat(lambda: asyncio_barrier_us(10, args.steps))
    results["baseline"]["asyncio_10_tasks_us"] = base
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        for plugin in ("Noop", "Relay"):
            for n in (1, 10, 100):
                steps = max(200, args.steps // n)
                us = repeat(lambda n=n, plugin=plugin, steps=steps: caviar_step_us(n, plugin, steps, tmp), 3)
                results["caviar"].append({"plugin": plugin, "modules": n, "step_us": us,
                                          "per_module_us": us / n, "ratio_to_asyncio_10": us / base})
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")

    print(f"asyncio barrier, 10 tasks: {base:.1f} µs per round (baseline, same run)\n")
    print("| Python plugins | modules | µs per step | µs per module | × asyncio(10) |")
    print("|---|---:|---:|---:|---:|")
    for r in results["caviar"]:
        print(f"| {r['plugin']} | {r['modules']} | {r['step_us']:.1f} | {r['per_module_us']:.1f} | "
              f"{r['ratio_to_asyncio_10']:.2f} |")
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
