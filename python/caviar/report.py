"""Figures of recorded runs, as in the paper's benchmarking section: per-module
resource bars for each run, and total wall clock across runs.

    caviar-core report RUN_DIR [RUN_DIR ...] [--labels 1 3 5 10] [--out report/]

Writes ``modules.png`` (per module and run: mean wall time per step, CPU time per
step, largest resident memory) and ``wall_clock.png`` (total wall clock per run),
plus ``report.json`` with the numbers.

Plugin packages add the figures of their own topics: a function ``figures(log, out)
-> list[path]`` registered in entry-point group ``caviar.report`` is called with each
run (:class:`caviar.RunLog`) and the directory to draw in (``OUT``, or ``OUT/LABEL``
for several runs); it draws nothing for a run without its topics.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
from importlib.metadata import entry_points

from caviar.runlog import load_run


def summary(run_dir) -> dict:
    log = load_run(run_dir)
    times = log.module_times()
    steps = max(1, int(log.status.get("steps_done") or 0))
    modules = {r["module"]: {"wall_s_per_step": r["wall_s"] / steps, "cpu_s_per_step": r["cpu_s"] / steps,
                             "max_rss_mib": r["max_rss_mib"], "share": r["share"],
                             "mean_gpu_util_pct": r["mean_gpu_util_pct"], "max_gpu_mem_mib": r["max_gpu_mem_mib"]}
               for r in times.iter_rows(named=True)}
    return {"run": str(run_dir), "steps": steps, "wall_s": log.status.get("wall_s"),
            "virtual_time_s": log.status.get("virtual_time_s"), "rtf": log.status.get("rtf"), "modules": modules}


def grouped(modules: dict) -> dict:
    """Modules named alike but for a trailing number (uav1 … uav20) as one bar: summed
    times, largest memory."""
    out: dict[str, dict] = {}
    for name, m in modules.items():
        key = re.sub(r"\d+$", "*", name) if re.search(r"\d+$", name) else name
        g = out.setdefault(key, {"wall_s_per_step": 0.0, "cpu_s_per_step": 0.0, "max_rss_mib": 0.0})
        g["wall_s_per_step"] += m["wall_s_per_step"]
        g["cpu_s_per_step"] += m["cpu_s_per_step"]
        g["max_rss_mib"] = max(g["max_rss_mib"], m["max_rss_mib"])
        for k in ("mean_gpu_util_pct", "max_gpu_mem_mib"):  # absent without a GPU
            if m.get(k) is not None:
                g[k] = max(g.get(k, 0.0), m[k])
    return out


def draw(summaries: list[dict], labels: list[str], out: pathlib.Path, xlabel: str = "run") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out.mkdir(parents=True, exist_ok=True)
    groups = [grouped(s["modules"]) for s in summaries]
    modules = list(dict.fromkeys(m for g in groups for m in g))
    panels = [("wall_s_per_step", 1e3, "wall time per step (ms)"), ("cpu_s_per_step", 1e3, "CPU time per step (ms)"),
              ("max_rss_mib", 1.0, "resident memory of the process (MiB)")]
    if any("max_gpu_mem_mib" in m for g in groups for m in g.values()):  # the paper's GPU panels
        panels += [("mean_gpu_util_pct", 1.0, "GPU utilisation (%)"), ("max_gpu_mem_mib", 1.0, "GPU memory (MiB)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4))
    width = 0.8 / max(1, len(summaries))
    x = np.arange(len(modules))
    for i, (g, label) in enumerate(zip(groups, labels, strict=False)):
        for ax, (key, scale, _) in zip(axes, panels, strict=True):
            ax.bar(x + i * width, [scale * g.get(m, {}).get(key, 0.0) for m in modules], width, label=label)
    axes[0].set_yscale("symlog", linthresh=1.0)
    axes[1].set_yscale("symlog", linthresh=1.0)
    for ax, title in zip(axes, (p[2] for p in panels), strict=True):
        ax.set_xticks(x + width * (len(summaries) - 1) / 2, modules, rotation=30, ha="right")
        ax.set_title(title)
        ax.grid(True, axis="y")
    axes[0].legend(title=xlabel)
    fig.tight_layout()
    fig.savefig(out / "modules.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    try:
        xs = [float(label) for label in labels]
    except ValueError:
        xs = list(range(len(labels)))
        ax.set_xticks(xs, labels)
    ax.plot(xs, [s["wall_s"] for s in summaries], "o-")
    ax.set(xlabel=xlabel, ylabel="total wall clock (s)", title="Wall clock")
    ax.grid(True)
    fig.tight_layout()
    fig.savefig(out / "wall_clock.png", dpi=100)
    plt.close(fig)
    (out / "report.json").write_text(json.dumps({"labels": labels, "runs": summaries}, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="caviar-core report", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=pathlib.Path)
    ap.add_argument("--labels", nargs="+", help="one per run (default: directory names)")
    ap.add_argument("--xlabel", default="run")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("report"))
    args = ap.parse_args(argv)
    labels = args.labels or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        ap.error(f"--labels: expected {len(args.runs)} labels, got {len(labels)}")
    try:
        summaries = [summary(r) for r in args.runs]
    except FileNotFoundError as e:
        print(f"error: {e}")
        return 2
    draw(summaries, labels, args.out, args.xlabel)
    written = [args.out / n for n in ("modules.png", "wall_clock.png", "report.json")]
    for run, label in zip(args.runs, labels, strict=True):
        written += plugin_figures(run, args.out / label if len(args.runs) > 1 else args.out)
    print(", ".join(map(str, written)))
    return 0


def plugin_figures(run: pathlib.Path, out: pathlib.Path) -> list[pathlib.Path]:
    """The figures every ``caviar.report`` entry point draws of ``run``."""
    log = load_run(run)
    written: list[pathlib.Path] = []
    for ep in sorted(entry_points(group="caviar.report"), key=lambda e: e.name):
        written += ep.load()(log, out)
    return written
