"""The SAR mission with its network option (blueprints/sar/network.toml) against the main
job (blueprints/sar/config.toml), one after the other on this machine, each in its own process.

In the main job the UAV hovers S = 320 Mbit / throughput at each rescue (the paper's). With the
network option the camera frames and each rescue's 10 × 4 MB go uplink through radio-network's
queues (Sionna SYS on the ray-traced channel, PUSCH with power control, SSB beams): the detector
sees a frame once it is delivered and the UAV hovers until its upload is through.

Writes ``docs/results/sar-network.json`` (T_p/T_v of each, the split of a network step, the
missions' outcomes, each rescue's hover, the frames' and uploads' delays) and
``docs/results/sar-network.png`` (hover per rescue; CDF of the frames' delay).

    .venv/bin/python benches/bench_sar_network.py [--network-run DIR] [--sar-run DIR]

``--network-run`` / ``--sar-run``: summarise an existing run of that blueprint instead of
running it again.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benches"))
from bench_common import machine  # noqa: E402

BIN = pathlib.Path(sys.executable).parent
OUT = ROOT / "docs" / "results"


def run(config: str, out: pathlib.Path, existing: str | None) -> tuple[pathlib.Path, float | None]:
    """The run directory of ``config`` (run now, or ``existing``) and its process time."""
    if existing:
        return pathlib.Path(existing), None
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    subprocess.run([str(BIN / "caviar-core"), "run", str(ROOT / "blueprints" / "sar" / config), "--out", str(out),
                    "-q"], check=True, capture_output=True)
    return out, time.perf_counter() - t0


def outcome(run_dir: pathlib.Path, process_s: float | None) -> dict:
    import caviar
    from caviar.report import summary

    s = summary(run_dir)
    log = caviar.load_run(run_dir)
    result = log.decoded("mission.result")[-1].data
    rescues = [m.data for m in log.decoded("mission.rescue")]
    out = {"tp_tv": round(s["wall_s"] / s["virtual_time_s"], 4), "wall_s": round(s["wall_s"], 1),
           "virtual_s": s["virtual_time_s"], "steps": s["steps"], "rescued": result["rescued"],
           "mission_time_s": result["mission_time_s"],
           "hover_s": [round(r["hover_s"], 2) if r.get("hover_s") is not None else None for r in rescues],
           "hover_total_s": round(sum(r["hover_s"] or 0.0 for r in rescues), 2),
           "module_s_per_step": {k: round(v["wall_s_per_step"], 5) for k, v in s["modules"].items()}}
    if process_s is not None:
        out["tp_tv_process"] = round(process_s / s["virtual_time_s"], 4)
    transfers = [m.data for m in log.decoded("network.transfers")]
    for name, source in (("frames", "3D.camera."), ("uploads", "mission.upload")):
        done = [x for x in transfers if x["source"].startswith(source) and not x.get("lost")]
        if done:
            delay = np.array([x["delay_s"] for x in done])
            out[name] = {"delivered": len(done), "lost": sum(1 for x in transfers if x["source"].startswith(source)
                                                             and x.get("lost")),
                         "delay_s": {p: round(float(np.percentile(delay, q)), 4)
                                     for p, q in (("p5", 5), ("p50", 50), ("p95", 95), ("max", 100))},
                         "upt_mbps_p50": round(float(np.median([x["upt_mbps"] for x in done])), 3)}
    ue = [m.data for m in log.decoded("network.ue")]
    if ue:
        ul = [u["ul_sinr_db"] for u in ue if u.get("ul_sinr_db") is not None]
        out["ul_sinr_db_p50"] = round(float(np.median(ul)), 2)
        out["ul_queue_bytes_max"] = max(u.get("ul_queue_bytes", 0) for u in ue)
    return out


def figure(sar: pathlib.Path, network: pathlib.Path, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import caviar

    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 4))
    for k, (label, run_dir) in enumerate((("S = 320 Mbit / throughput (config.toml)", sar),
                                          ("until the uplink delivered (network.toml)", network))):
        rescues = [m.data for m in caviar.load_run(run_dir).decoded("mission.rescue")]
        hover = [r["hover_s"] or 0.0 for r in rescues]
        a0.bar(np.arange(len(hover)) + 0.4 * k, hover, width=0.4, label=label)
    a0.set(xlabel="rescue", ylabel="hover (s)", yscale="log", title="hover per rescue")
    a0.legend(fontsize=8)
    frames = [m.data["delay_s"] for m in caviar.load_run(network).decoded("network.transfers")
              if m.data["source"].startswith("3D.camera.") and not m.data.get("lost")]
    v = np.sort(frames)
    a1.step(v * 1e3, np.arange(1, v.size + 1) / v.size, where="post")
    a1.set(xlabel="frame delay, queued to delivered (ms)", ylabel="CDF", xscale="log",
           title=f"camera frames over the uplink ({v.size})")
    a1.grid(True)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--network-run", help="an existing run of blueprints/sar/network.toml")
    ap.add_argument("--sar-run", help="an existing run of blueprints/sar/config.toml")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sar_dir, sar_s = run("config.toml", pathlib.Path(tmp) / "sar", args.sar_run)
        net_dir, net_s = run("network.toml", pathlib.Path(tmp) / "network", args.network_run)
        result = {"machine": machine(),
                  "what": "SAR main job (blueprints/sar/config.toml) against its network option "
                          "(blueprints/sar/network.toml), one process each",
                  "sar": outcome(sar_dir, sar_s), "sar_network": outcome(net_dir, net_s)}
        figure(sar_dir, net_dir, OUT / "sar-network.png")
    (OUT / "sar-network.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: {x: v[x] for x in ("tp_tv", "rescued", "mission_time_s", "hover_total_s")}
                      for k, v in result.items() if isinstance(v, dict)}, indent=1))


if __name__ == "__main__":
    main()
