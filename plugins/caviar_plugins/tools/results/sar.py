"""Runs the SAR blueprint with random, decision-tree and oracle beam selection and
writes the paper's mission table (mission time, rescued targets) with plots and the
exact configurations that produced it.

    python -m caviar_plugins.tools.results.sar --tree models/beam-tree.pkl [--out docs/results]
    python -m caviar_plugins.tools.results.sar --config blueprints/sar-paper/config.toml \
        --tree models/paper-beam-tree.pkl --knn models/paper-beam-knn.pkl \
        --methods random tree oracle knn --runs runs/paper --out docs/results/paper-protocol --reuse

``knn`` is the better selector (:mod:`caviar_plugins.beam_selection.knn`) in the loop,
run as the ``tree`` method with its model. ``--reuse`` keeps completed runs.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
from typing import Any

import numpy as np

import caviar
from caviar.rundir import RunDir
from caviar_plugins.schema import IMAGE_QUALITY, POSITIONS, RESCUE, RESULT, THROUGHPUT, read_position

PAPER = {"random": (424.94, 3), "tree": (98.50, 5), "oracle": (75.53, 5)}
LABEL = {"random": "Random", "tree": "Decision tree", "oracle": "Oracle",
         "knn": "k-NN gain + previous sweep (ours)", "previous": "Previous beam (ours)",
         "sweep": "Sweep forest (ours)"}
MODEL_METHODS = ("tree", "knn", "sweep")
"""Methods run as the selector's ``tree`` method with a pickled model."""


def run_all(config: pathlib.Path, tree: pathlib.Path, runs: pathlib.Path, methods, overrides=(),
            knn: pathlib.Path | None = None, reuse: bool = False, sweep: pathlib.Path | None = None) -> dict:
    logs = {}
    for method in methods:
        out = runs / f"sar-{method}"
        done = RunDir(out).completed()
        if reuse and done:
            print(f"reusing {out}", flush=True)
            logs[method] = caviar.load_run(out)
            continue
        if out.exists():
            shutil.rmtree(out)
        sets = {"modules.beams.params.method": "tree" if method in MODEL_METHODS else method,
                "output.name": f"sar-{method}"}
        if method in MODEL_METHODS:
            model = {"tree": tree, "knn": knn, "sweep": sweep}[method]
            assert model is not None, f"{method}: no model file given"
            # Relative to the config file, as paths in it are: the saved config stays portable.
            sets["modules.beams.params.model"] = os.path.relpath(model.resolve(), config.resolve().parent)
        sim = caviar.Simulation.from_toml(config, overrides=[f"{k}={json.dumps(v)}" for k, v in sets.items()]
                                          + list(overrides), out=out)
        print(f"running {method} -> {out}", flush=True)
        logs[method] = sim.run(progress=True)
    return logs


def summarise(logs: dict) -> list[dict]:
    rows = []
    for method, log in logs.items():
        res = log.topic(RESULT)
        if res.height:
            result = res.row(0, named=True)
        else:  # the episode hit its step limit before the mission ended: a lower bound
            offset = _clock_offset(log)
            rescues = log.topic(RESCUE)
            result = {"mission_time_s": offset + float(log.topic(POSITIONS)["time"].max()),
                      "rescued": rescues.height, "clock_offset_s": offset}
        extra: dict[str, Any] = {"ended": bool(res.height)}
        if not res.height:
            extra["steps_limit"] = log.status.get("steps_planned")
            if rescues.height:  # the hover the UAV was serving or about to serve
                extra["last_rescue_hover_s"] = float(rescues["hover_s"][-1])
                extra["last_rescue_throughput_mbps"] = float(rescues["throughput"][-1])
        extra.update({k: result[k] for k in ("clock_offset_s", "flight_time_s", "hover_s", "flown_m")
                      if result.get(k) is not None})
        paper_t, paper_r = PAPER.get(method, (None, None))
        if paper_t is not None:
            extra.update(paper_mission_time_s=paper_t, paper_rescued=paper_r,
                         diff_s=round(result["mission_time_s"] - paper_t, 2),
                         diff_pct=round(100 * (result["mission_time_s"] / paper_t - 1), 1))
        extra["rescued_at_a_person"] = _persons_rescued(log)
        thr = log.topic(THROUGHPUT)["throughput"].to_numpy()
        q = log.topic(IMAGE_QUALITY)
        psnr = np.minimum(q["psnr_db"].to_numpy(), 99.0)
        rows.append({"method": method, "mission_time_s": result["mission_time_s"], "rescued": result["rescued"],
                     **extra,
                     "throughput_mbps_mean": float(thr.mean()), "throughput_mbps_median": float(np.median(thr)),
                     "psnr_db_median": float(np.median(psnr)),
                     "frames_at_50pct_loss": float(np.mean(q["loss_rate"].to_numpy() == 0.5)),
                     "steps": log.status["steps_done"], "wall_s": log.status["wall_s"],
                     "run_dir": str(log.path)})
    return rows


def _persons_rescued(log, within_m: float = 5.0) -> int:
    """Rescues within ``within_m`` of a placed person (the rest are false detections)."""
    import tomllib

    from caviar_plugins.vision.camera import default_targets

    cam = tomllib.loads(log.config_text).get("modules", {}).get("camera", {}).get("params", {})
    targets = np.array(cam.get("targets") or default_targets(), dtype=float)
    return sum(1 for r in log.topic(RESCUE).iter_rows(named=True)
               if np.min(np.hypot(targets[:, 0] - r["x"], targets[:, 1] - r["y"])) < within_m)


def _clock_offset(log) -> float:
    """The flight's takeoff offset from the run's configuration (paper protocol), else 0."""
    import tomllib

    uav = tomllib.loads(log.config_text).get("modules", {}).get("uav", {}).get("params", {})
    return float(uav.get("takeoff_s", 8.5)) if uav.get("protocol") == "paper" else 0.0


def write(rows: list[dict], logs: dict, out: pathlib.Path, note: str = "") -> None:
    out.mkdir(parents=True, exist_ok=True)
    configs = out / "configs"
    configs.mkdir(exist_ok=True)
    for method, log in logs.items():
        shutil.copy(RunDir(log.path).config_file, configs / f"sar-{method}.toml")
    write_tables(rows, out, note)
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
    a2.set(xlabel="virtual time (s, without the takeoff offset)", ylabel="distance flown (m)",
           title="Progress (grey: rescues)")
    for a in (a1, a2):
        a.grid(True)
        a.legend()
    fig.tight_layout()
    fig.savefig(out / "mission-traces.png", dpi=100)
    plt.close(fig)


def write_tables(rows: list[dict], out: pathlib.Path, note: str = "") -> str:
    """mission.json, mission.md (paper | ours | difference side by side) and mission.png
    (bars, paper vs ours)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "mission.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = ["| approach | paper: time (s) | ours: time (s) | diff (s) | diff (%) | paper: rescued | ours: rescued "
             "(at a person) | diff | ours: hover total (s) | throughput mean / median (Mbit/s) | frames at 50 % loss |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        pt, pr = PAPER.get(r["method"], (None, None))
        t = r["mission_time_s"]
        ended = r.get("ended", True)
        diff = f"{t - pt:+.2f} | {100 * (t / pt - 1):+.1f}" if pt else "— | —"
        hover = f"{r['hover_s']:.1f}" if r.get("hover_s") is not None else "—"
        rescued_diff = f"{r['rescued'] - pr:+d}" if pr else "—"
        persons = f" ({r['rescued_at_a_person']})" if r.get("rescued_at_a_person") is not None else ""
        shown = f"{t:.2f}" if ended else f"> {t:.2f}"
        lines.append(f"| {LABEL[r['method']]} | {pt if pt else '—'} | {shown} | {diff} | {pr if pr else '—'} | "
                     f"{r['rescued']}{persons} | {rescued_diff} | {hover} | "
                     f"{r['throughput_mbps_mean']:.1f} / {r['throughput_mbps_median']:.1f} | "
                     f"{100 * r['frames_at_50pct_loss']:.0f} % |")
    table = "\n".join(lines)
    for r in rows:
        if not r.get("ended", True):
            table += (f"\n\n{LABEL[r['method']]}: the run was stopped at its step limit ({r.get('steps_limit')} steps) "
                      f"before the mission ended, so its time is a lower bound")
            if r.get("last_rescue_hover_s") is not None:
                table += (f"; its last rescue asked for a hover of {r['last_rescue_hover_s']:.1f} s "
                          f"(S = 320 Mbit / {r['last_rescue_throughput_mbps']:.4f} Mbit/s)")
            table += "."
    (out / "mission.md").write_text(f"# SAR mission\n\n{note}\n\n{table}\n")
    print(table)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    idx = np.arange(len(rows))
    ax.bar(idx - 0.2, [PAPER.get(r["method"], (np.nan,))[0] for r in rows], 0.4, label="paper")
    ax.bar(idx + 0.2, [r["mission_time_s"] for r in rows], 0.4, label="ours", color="tab:orange",
           hatch=[("" if r.get("ended", True) else "//") for r in rows])
    for i, r in enumerate(rows):
        bound = "" if r.get("ended", True) else "> "
        ax.annotate(f"{bound}{r['mission_time_s']:.0f} s\n{r['rescued']} rescued", (i + 0.2, r["mission_time_s"]),
                    ha="center", va="bottom", fontsize=8)
    ax.set(xticks=idx, xticklabels=[LABEL[r["method"]].replace(" (ours)", "\n(ours)").replace(" + ", " +\n")
                                    for r in rows], ylabel="mission time (s)", yscale="log",
           title=f"Mission time, paper vs ours ({out.name}; hatched: stopped, lower bound)")
    ax.grid(True, axis="y")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "mission.png", dpi=100)
    plt.close(fig)
    return table


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.results.sar", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", type=pathlib.Path, default=pathlib.Path("blueprints/sar/config.toml"))
    ap.add_argument("--tree", type=pathlib.Path, default=pathlib.Path("models/beam-tree.pkl"))
    ap.add_argument("--runs", type=pathlib.Path, default=pathlib.Path("runs"))
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results"))
    ap.add_argument("--methods", nargs="+", default=["random", "tree", "oracle"])
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--knn", type=pathlib.Path, default=pathlib.Path("models/paper-beam-knn.pkl"))
    ap.add_argument("--sweep", type=pathlib.Path, default=pathlib.Path("models/paper-beam-sweep-forest.pkl"))
    ap.add_argument("--reuse", action="store_true", help="keep completed runs in --runs")
    ap.add_argument("--note", default="", help="text above the table in mission.md")
    args = ap.parse_args()
    logs = run_all(args.config, args.tree, args.runs, args.methods, args.overrides, knn=args.knn, reuse=args.reuse,
                   sweep=args.sweep)
    write(summarise(logs), logs, args.out, args.note)


if __name__ == "__main__":
    main()
