"""Runs the SAR blueprint with random, decision-tree and oracle beam selection and
writes the paper's mission table (mission time, rescued targets) with plots and the
exact configurations that produced it.

    python -m caviar_plugins.sar.results --tree models/beam-tree.pkl [--out docs/results]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil

import numpy as np

import caviar
from caviar_plugins.schema import IMAGE_QUALITY, POSITIONS, RESCUE, RESULT, THROUGHPUT, read_position

PAPER = {"random": (424.94, 3), "tree": (98.50, 5), "oracle": (75.53, 5)}
LABEL = {"random": "Random", "tree": "Decision tree", "oracle": "Oracle"}


def run_all(config: pathlib.Path, tree: pathlib.Path, runs: pathlib.Path, methods, overrides=()) -> dict:
    logs = {}
    for method in methods:
        out = runs / f"sar-{method}"
        if out.exists():
            shutil.rmtree(out)
        sets = {"modules.beams.params.method": method, "output.name": f"sar-{method}"}
        if method == "tree":
            # Relative to the config file, as paths in it are: the saved config stays portable.
            sets["modules.beams.params.model"] = os.path.relpath(tree.resolve(), config.resolve().parent)
        sim = caviar.Simulation.from_toml(config, overrides=[f"{k}={json.dumps(v)}" for k, v in sets.items()]
                                          + list(overrides), out=out)
        print(f"running {method} -> {out}", flush=True)
        logs[method] = sim.run(progress=True)
    return logs


def summarise(logs: dict) -> list[dict]:
    rows = []
    for method, log in logs.items():
        result = log.topic(RESULT).row(0, named=True)
        thr = log.topic(THROUGHPUT)["throughput"].to_numpy()
        q = log.topic(IMAGE_QUALITY)
        psnr = np.minimum(q["psnr_db"].to_numpy(), 99.0)
        rows.append({"method": method, "mission_time_s": result["mission_time_s"], "rescued": result["rescued"],
                     "throughput_mbps_mean": float(thr.mean()), "throughput_mbps_median": float(np.median(thr)),
                     "psnr_db_median": float(np.median(psnr)),
                     "frames_at_50pct_loss": float(np.mean(q["loss_rate"].to_numpy() == 0.5)),
                     "steps": log.status["steps_done"], "wall_s": log.status["wall_s"],
                     "run_dir": str(log.path)})
    return rows


def write(rows: list[dict], logs: dict, out: pathlib.Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    configs = out / "configs"
    configs.mkdir(exist_ok=True)
    for method, log in logs.items():
        shutil.copy(log.path / "config.toml", configs / f"sar-{method}.toml")
    (out / "mission.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = ["| approach | mission time (s) | rescued targets | paper: time (s) | paper: rescued | "
             "throughput mean / median (Mbit/s) | median PSNR (dB) | frames at 50 % loss |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        pt, pr = PAPER[r["method"]]
        lines.append(f"| {LABEL[r['method']]} | {r['mission_time_s']:.2f} | {r['rescued']} | {pt} | {pr} | "
                     f"{r['throughput_mbps_mean']:.1f} / {r['throughput_mbps_median']:.1f} | "
                     f"{r['psnr_db_median']:.1f} | {100 * r['frames_at_50pct_loss']:.0f} % |")
    (out / "mission.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4))
    for method, log in logs.items():
        thr = log.topic(THROUGHPUT)
        a1.plot(thr["time"], thr["throughput"], label=LABEL[method], lw=1)
        pos = log.topic(POSITIONS)
        xy = np.array([read_position(row)[:2] for row in pos.iter_rows(named=True)])
        flown = np.cumsum(np.r_[0, np.linalg.norm(np.diff(xy, axis=0), axis=1)])
        a2.plot(pos["time"], flown, label=LABEL[method])
        for r in log.topic(RESCUE).iter_rows(named=True):
            a2.axvline(r["time"], color="gray", lw=0.5)
    a1.set(xlabel="virtual time (s)", ylabel="throughput (Mbit/s)", title="Throughput of the selected beam pair")
    a2.set(xlabel="virtual time (s)", ylabel="distance flown (m)", title="Progress (grey: rescues)")
    for a in (a1, a2):
        a.grid(True)
        a.legend()
    fig.tight_layout()
    fig.savefig(out / "mission.png", dpi=100)


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.sar.results", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", type=pathlib.Path, default=pathlib.Path("blueprints/sar/config.toml"))
    ap.add_argument("--tree", type=pathlib.Path, default=pathlib.Path("models/beam-tree.pkl"))
    ap.add_argument("--runs", type=pathlib.Path, default=pathlib.Path("runs"))
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results"))
    ap.add_argument("--methods", nargs="+", default=["random", "tree", "oracle"])
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    logs = run_all(args.config, args.tree, args.runs, args.methods, args.overrides)
    write(summarise(logs), logs, args.out)


if __name__ == "__main__":
    main()
