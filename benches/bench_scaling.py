"""Resource and scaling benchmark, as the paper's last section: the SAR loop with
1, 3, 5, 10 (then 20, 50 …) UAVs, all capturing images for the detector, no rescue
stops; per-module wall, CPU and memory, and the total wall clock.

    .venv/bin/python benches/bench_scaling.py [--uavs 1 3 5 10] [--duration 60] [--samples 1000000]

Writes bench-results/scaling/{sweep.json,modules.png,wall_clock.png} (the figures of
``caviar-core report``) and prints a table. ``--from-runs`` only summarises and draws the
``run-N`` folders already under ``--out`` (a sweep recorded on another machine, say). The
paper ran 60 s of virtual time at Ts = 0.5 s with 1e6 samples per source on a GPU.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil

import caviar
from caviar.report import draw, summary
from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints

ROUTE = "central_park_path0_scene.csv"


def config(n: int, duration: float, samples: int, uav_extra: str = "", camera: str = "", comm: str = "",
           detector: str = "") -> str:
    """The SAR loop with ``n`` UAVs spread along the route. ``uav_extra`` (TOML lines) is added
    to each UAV's params; ``camera``, ``comm`` and ``detector`` (inline-table entries) to
    those modules' params (benches/bench_perf_steps.py switches code paths with them)."""
    length = Path(read_waypoints(DATA / ROUTE)).length
    text = f"""
[episode]
ts = 0.5
duration = {duration}
seed = 1
stages = ["mobility", "camera", "communications", "link", "detection"]

[output]
exclude = ["3D.camera.>", "ai.images.>"]
"""
    for i in range(n):
        # Spread along the route; each flies on (and stays at the end) without stopping.
        text += f"""
[modules.uav{i + 1}]
stage = "mobility"
plugin = "waypoint-flight"
[modules.uav{i + 1}.params]
waypoints = "{ROUTE}"
frame = "scene"
ue_id = "uav{i + 1}"
end_at_last = false
start_m = {i * length / n:.1f}
{uav_extra}"""
    comm = f"raytracing = {{ samples_per_src = {samples} }}, publish_channels = false" + (f", {comm}" if comm else "")
    camera_params = f"params = {{ {camera} }}\n" if camera else ""
    detector_params = f"params = {{ {detector} }}\n" if detector else ""
    text += f"""
[modules.camera]
stage = "camera"
plugin = "camera"
{camera_params}
[modules.comm]
stage = "communications"
plugin = "sionna-link"
params = {{ {comm} }}

[modules.link]
stage = "link"
plugin = "image-link"

[modules.detector]
stage = "detection"
plugin = "person-detector"
{detector_params}"""
    return text


def table(summaries: list[dict]) -> str:
    """The Markdown table of docs/measured/performance.md; GPU columns where the runs recorded them."""
    gpu = summaries[0]["modules"]["comm"].get("max_gpu_mem_mib") is not None
    head = ("| UAVs | wall clock (s) | × 1 UAV | ray tracing (ms/step) | camera (ms/step) | detector (ms/step) | "
            "engine (ms/step) | engine share | max RSS (MiB) |")
    if gpu:
        head += " ray tracing GPU util (%) | GPU memory (MiB) |"
    lines = [head, "|" + "---:|" * (head.count("|") - 1)]
    base = summaries[0]
    for s in summaries:
        m = s["modules"]
        line = (f"| {s['uavs']} | {s['wall_s']:.1f} | {s['wall_s'] / base['wall_s']:.2f} | "
                f"{1e3 * m['comm']['wall_s_per_step']:.0f} | {1e3 * m['camera']['wall_s_per_step']:.0f} | "
                f"{1e3 * m['detector']['wall_s_per_step']:.0f} | {1e3 * m['caviar.core']['wall_s_per_step']:.2f} | "
                f"{100 * m['caviar.core']['share']:.3f} % | {max(v['max_rss_mib'] for v in m.values()):.0f} |")
        if gpu:
            gpu_mem = max(v["max_gpu_mem_mib"] or 0 for v in m.values())
            line += f" {m['comm']['mean_gpu_util_pct']:.1f} | {gpu_mem:.0f} |"
        lines.append(line)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--uavs", nargs="+", type=int, default=[1, 3, 5, 10])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("bench-results/scaling"))
    ap.add_argument("--from-runs", action="store_true", help="summarise the run-N folders under --out, run nothing")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    summaries = []
    for n in args.uavs:
        run = args.out / f"run-{n}"
        if not args.from_runs:
            cfg = args.out / f"uavs-{n}.toml"
            cfg.write_text(config(n, args.duration, args.samples))
            if run.exists():
                shutil.rmtree(run)
            print(f"{n} UAVs ...", flush=True)
            caviar.Simulation.from_toml(cfg, out=run).run()
        s = summary(run)
        s["uavs"] = n
        summaries.append(s)
        m = s["modules"]
        print(f"{n:3d} UAVs: wall {s['wall_s']:.1f} s for {s['virtual_time_s']:.0f} s virtual; "
              f"comm {1e3 * m['comm']['wall_s_per_step']:.0f} ms/step, "
              f"camera {1e3 * m['camera']['wall_s_per_step']:.0f}, "
              f"detector {1e3 * m['detector']['wall_s_per_step']:.0f}, "
              f"engine {1e3 * m['caviar.core']['wall_s_per_step']:.2f}; "
              f"RSS {max(v['max_rss_mib'] for v in m.values()):.0f} MiB", flush=True)
    draw(summaries, [str(n) for n in args.uavs], args.out, xlabel="UAVs")
    print()
    print(table(summaries))
    (args.out / "sweep.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                     "runs": summaries}, indent=2) + "\n")


if __name__ == "__main__":
    main()
