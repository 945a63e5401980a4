"""The radio network's host-time proxy before and after a change, alternated (issue #53): on a
machine whose timings wander from run to run (a 2-core VM: torch's dispatch reads 3 to 7 µs a
call from one run to the next), one run of each says little; this runs
``bench_host_overhead.py --one N`` for a baseline checkout's plugins and for this one in turn,
``--rounds`` times, each in a process of its own, and reports every run's figures and their medians.

    git archive REV plugins benches | tar -x -C /tmp/base
    .venv/bin/python benches/bench_host_alternated.py --baseline /tmp/base [--ues 1000] [--rounds 3] \
        [--groups-per-call 25 --baseline-groups-per-call 5]   # (the committed file's)

Writes ``docs/results/host-overhead-alternated.json``. Run with ``OMP_NUM_THREADS=1`` (see
``bench_host_overhead.py``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics

from bench_common import machine
from bench_host_overhead import ROOT, _subprocess

OUT = ROOT / "docs" / "results" / "host-overhead-alternated.json"
FIGURES = ("host_proxy_with_launches_ms", "host_python_numpy_ms", "host_proxy_cpu_with_launches_ms",
           "host_python_numpy_cpu_ms", "compiled_entries_ms_per_step", "torch_calls_per_step", "dispatch_us_wall")
"""Each run's figures kept (``bench_host_overhead.one``'s)."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, help="another checkout's root (its plugins/ are the 'before')")
    ap.add_argument("--ues", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--groups-per-call", type=int, default=5)
    ap.add_argument("--baseline-groups-per-call", type=int, default=None,
                    help="the baseline's (default: --groups-per-call), where its best setting differs")
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    args = ap.parse_args()
    if not 1 <= args.rounds <= 9:
        ap.error(f"--rounds: expected 1 to 9, got {args.rounds}")
    plugins = {"before": str(pathlib.Path(args.baseline) / "plugins"), "after": None}
    groups = {"before": args.baseline_groups_per_call or args.groups_per_call, "after": args.groups_per_call}
    runs: dict[str, list[dict]] = {"before": [], "after": []}
    for k in range(args.rounds):
        for name, path in plugins.items():
            r = _subprocess(["--one", str(args.ues), "--groups-per-call", str(groups[name])], path)
            runs[name].append({f: r[f] for f in FIGURES})
            print(f"round {k + 1}/{args.rounds} {name}", json.dumps(runs[name][-1]), flush=True)
    medians = {name: {f: statistics.median(r[f] for r in rs) for f in FIGURES} for name, rs in runs.items()}
    result = {"machine": machine(), "ues": args.ues, "cells": 21, "groups_per_call": groups,
              "rounds": args.rounds, "baseline": str(args.baseline),
              "method": "bench_host_overhead.py --one, the baseline's plugins and this checkout's in turn, "
                        "each run in a process of its own; medians over the rounds",
              "runs": runs, "medians": medians,
              "ratio_before_after_of_medians": {f: round(medians["before"][f] / max(medians["after"][f], 1e-9), 2)
                                                for f in FIGURES}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({"medians": medians, "ratios": result["ratio_before_after_of_medians"]}, indent=1))


if __name__ == "__main__":
    main()
