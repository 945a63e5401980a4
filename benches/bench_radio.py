"""Communications benchmarks on the Central Park scene (paper settings unless stated).

    .venv/bin/python benches/bench_radio.py overhead [--steps 5] [--samples 1000000]
    .venv/bin/python benches/bench_radio.py accuracy [--spacing 10]

``overhead``: per-step time of the sionna-link plugin run by the engine against a
bare Sionna RT call (PathSolver + CFR at the carrier, same scene, settings and
receiver positions), interleaved step by step in the same run, for 1, 3, 5 and 10
receivers.

``accuracy``: the speed/accuracy trade-off of the sample count over the paper's
flight: against the 1e6-sample reference, how often the best beam pair is the same,
how often the reference pair is among the top 3, and the throughput error.

Results go to bench-results/radio-*.json (and a PNG plot for ``accuracy``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

import caviar
from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.radio import LinkBudget, RadioConfig, RadioScene
from caviar_plugins.rt import configure_drjit
from caviar_plugins.rt.scene import scene_path
from caviar_plugins.rt.settings import with_raytracing
from caviar_plugins.schema import POSITIONS, position_payload

configure_drjit()  # before Sionna RT, Mitsuba or Dr.Jit are imported (none of the above imports them)

OUT = pathlib.Path("bench-results")
FLIGHT = DATA / "central_park_path0_scene.csv"


def machine() -> dict:
    """The machine as it is (:func:`caviar_plugins.machine.describe`: CPU, GPU, Dr.Jit variant, torch device)."""
    from caviar_plugins.machine import describe

    return describe()


def flight_positions(n_rx: int, steps: int, ts: float = 0.5, speed: float = 5.0) -> list[dict[str, np.ndarray]]:
    """Receivers spread along the flight, each advancing speed·ts per step."""
    path = Path(read_waypoints(FLIGHT))
    starts = np.linspace(0, path.length * 0.9, n_rx)
    return [{f"uav{i + 1}": path.at(s + k * speed * ts) for i, s in enumerate(starts)} for k in range(steps)]


def bare_solver(cfg: RadioConfig):
    """The bare Sionna RT calls, as a user would write them without caviar."""
    import sionna.rt as rt

    scene = rt.load_scene(str(scene_path(cfg.scene)))
    scene.frequency = cfg.frequency_hz
    arr = lambda s: rt.PlanarArray(num_rows=s[0], num_cols=s[1], vertical_spacing=cfg.spacing,  # noqa: E731
                                   horizontal_spacing=cfg.spacing, pattern=cfg.pattern, polarization=cfg.polarization)
    scene.tx_array, scene.rx_array = arr(cfg.tx_array), arr(cfg.rx_array)
    scene.add(rt.Transmitter("tx", position=cfg.tx_position, orientation=cfg.tx_orientation))
    solver = rt.PathSolver()
    receivers = {}

    def solve(positions):
        for k, p in positions.items():
            p = (np.asarray(p) + cfg.antenna_offset).tolist()
            if k not in receivers:
                receivers[k] = rt.Receiver(k, position=p)
                scene.add(receivers[k])
            else:
                receivers[k].position = p
        paths = solver(scene, max_depth=cfg.max_depth, samples_per_src=cfg.samples_per_src, synthetic_array=True,
                       los=cfg.los, specular_reflection=cfg.specular_reflection,
                       diffuse_reflection=cfg.diffuse_reflection, refraction=cfg.refraction,
                       diffraction=cfg.diffraction, seed=0)
        return paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")

    return solve


def overhead(args) -> None:
    results = {"machine": machine(), "samples_per_src": args.samples, "steps": args.steps, "rows": []}
    # The plugin's own overhead over the same Sionna calls: without the shoot cache.
    cfg = with_raytracing(RadioConfig, samples_per_src=args.samples, uav_mesh=False, shoot_cache=False)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        for n_rx in (1, 3, 5, 10):
            steps = args.steps + 1  # the first step compiles kernels: not counted
            positions = flight_positions(n_rx, steps)
            text = '[episode]\nts = 0.5\nsteps = %d\nstages = ["mobility", "communications"]\n' % steps
            text += '[output]\nexclude = ["communications.channel.>", "communications.beam_gains.>"]\n'
            for k in positions[0]:
                text += (f'[modules.{k}]\nstage = "mobility"\nplugin = "caviar.replay"\n'
                         f'params = {{ run = "positions-{n_rx}", sources = ["{k}"] }}\n')
            text += (f'[modules.comm]\nstage = "communications"\nplugin = "sionna-link"\n'
                     f'params = {{ samples_per_src = {args.samples}, uav_mesh = false, shoot_cache = false }}\n')
            record_positions(tmp / f"positions-{n_rx}", positions)
            (tmp / f"bench-{n_rx}.toml").write_text(text)
            sim = caviar.Simulation.from_toml(tmp / f"bench-{n_rx}.toml", out=tmp / f"run-{n_rx}")
            bare = bare_solver(cfg)
            bare_s = []
            for k in range(steps):
                sim.step()
                t0 = time.perf_counter()
                bare(positions[k])
                bare_s.append(time.perf_counter() - t0)
            sim.close()
            timings = caviar.load_run(tmp / f"run-{n_rx}").timings
            plugin_s = timings.filter(timings["module"] == "comm")["wall_s"].to_list()
            core_s = timings.filter(timings["module"] == "caviar.core")["wall_s"].to_list()
            row = {"receivers": n_rx, "bare_s": statistics.median(bare_s[1:]),
                   "plugin_s": statistics.median(plugin_s[1:]), "core_s": statistics.median(core_s[1:]),
                   "bare_all": bare_s, "plugin_all": plugin_s}
            row["overhead_pct"] = 100 * (row["plugin_s"] - row["bare_s"]) / row["bare_s"]
            results["rows"].append(row)
            print(f"{n_rx:3d} rx: bare {row['bare_s']:.3f} s  plugin {row['plugin_s']:.3f} s  "
                  f"({row['overhead_pct']:+.1f} %)  engine {1e3 * row['core_s']:.2f} ms", flush=True)
    write(results, "radio-overhead")
    print("\n| receivers | bare Sionna RT (s/step) | sionna-link plugin (s/step) | difference | engine (ms/step) |")
    print("|---:|---:|---:|---:|---:|")
    for r in results["rows"]:
        print(f"| {r['receivers']} | {r['bare_s']:.2f} | {r['plugin_s']:.2f} | {r['overhead_pct']:+.1f} % | "
              f"{1e3 * r['core_s']:.2f} |")


def record_positions(run_dir: pathlib.Path, positions: list[dict]) -> None:
    """Records the positions as a run of its own, for caviar.replay."""
    import polars as pl

    run_dir.mkdir(parents=True)
    rows = []
    for k, step in enumerate(positions):
        for ue, p in step.items():
            rows.append({"step": k, "time": 0.5 * k, "seq": len(rows), "source": ue, "topic": POSITIONS,
                         "kind": "json", "meta": None, "data": None, "text": json.dumps(position_payload(ue, p))})
    frame = pl.DataFrame(rows, schema={"step": pl.UInt64, "time": pl.Float64, "seq": pl.UInt32, "source": pl.Utf8,
                                       "topic": pl.Utf8, "kind": pl.Utf8, "text": pl.Utf8, "meta": pl.Utf8,
                                       "data": pl.Binary})
    frame.write_parquet(run_dir / "messages.parquet")
    (run_dir / "run.json").write_text(json.dumps({"status": "completed"}))


def accuracy(args) -> None:
    path = Path(read_waypoints(FLIGHT))
    arcs = np.arange(0, path.length, args.spacing)
    budget = LinkBudget()
    # The reference is itself a Monte Carlo estimate: the same 1e6 samples with another
    # solver seed show its own noise floor.
    runs = [(10**4, 0), (3 * 10**4, 0), (10**5, 0), (3 * 10**5, 0), (10**6, 1), (10**6, 0)]
    per_count = {}
    for n, seed in runs:
        radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=n, uav_mesh=True), seed=seed)
        radio.place({"uav1": path.at(arcs[0])})
        radio.solve()  # compile
        gains, times, los = [], [], []
        for s in arcs:
            radio.place({"uav1": path.at(s)})
            t0 = time.perf_counter()
            link = radio.solve()["uav1"]
            times.append(time.perf_counter() - t0)
            gains.append(link.gains)
            los.append(link.los)
        per_count[(n, seed)] = (np.array(gains), np.array(times), np.array(los))
        print(f"{n:>8d} samples, seed {seed}: {np.median(times):.3f} s per solve", flush=True)
    ref = per_count[(10**6, 0)]
    ref_gains = ref[0].reshape(len(arcs), -1)
    ref_best = ref_gains.argmax(1)
    ref_thr = budget.throughput_mbps(ref_gains.max(1))
    rows = []
    for (n, seed), (gains, times, los) in per_count.items():
        g = gains.reshape(len(arcs), -1)
        best = g.argmax(1)
        top3 = np.argsort(-g, axis=1)[:, :3]
        # Throughput the link gets with this count's choice, in the reference channel.
        thr_choice = budget.throughput_mbps(ref_gains[np.arange(len(arcs)), best])
        thr_est = budget.throughput_mbps(g.max(1))
        rows.append({
            "samples": n, "seed": seed, "solve_s": float(np.median(times)),
            "speedup_vs_1e6": float(np.median(ref[1]) / np.median(times)),
            "same_best_pair_pct": float(100 * np.mean(best == ref_best)),
            "ref_pair_in_top3_pct": float(100 * np.mean([r in t for r, t in zip(ref_best, top3, strict=True)])),
            "throughput_loss_of_choice_mbps_mean": float(np.mean(ref_thr - thr_choice)),
            "throughput_loss_of_choice_mbps_p95": float(np.percentile(ref_thr - thr_choice, 95)),
            "throughput_estimate_error_mbps_median": float(np.median(np.abs(thr_est - ref_thr))),
            "los_agreement_pct": float(100 * np.mean(los == ref[2])),
        })
    results = {"machine": machine(), "positions": len(arcs), "spacing_m": args.spacing, "rows": rows,
               "reference_throughput_mbps": ref_thr.tolist(), "los": ref[2].tolist()}
    write(results, "radio-accuracy")
    print("\n| samples (seed) | s/solve | speed-up | same best pair | ref. pair in top 3 | "
          "loss of choice, mean (p95) | "
          "throughput estimate error (median) | LOS flag agrees |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['samples']:.0e} ({r['seed']}) | {r['solve_s']:.2f} | {r['speedup_vs_1e6']:.1f}× | "
              f"{r['same_best_pair_pct']:.0f} % | "
              f"{r['ref_pair_in_top3_pct']:.0f} % | {r['throughput_loss_of_choice_mbps_mean']:.2f} "
              f"({r['throughput_loss_of_choice_mbps_p95']:.2f}) Mbit/s | "
              f"{r['throughput_estimate_error_mbps_median']:.2f} Mbit/s | {r['los_agreement_pct']:.0f} % |")
    plot_accuracy(results, arcs, per_count, budget)


def plot_accuracy(results, arcs, per_count, budget) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4))
    for (n, seed), (g, _, _) in per_count.items():
        a1.plot(arcs, budget.throughput_mbps(g.reshape(len(arcs), -1).max(1)), label=f"{n:.0e} samples, seed {seed}")
    a1.set(xlabel="distance flown (m)", ylabel="best-pair throughput (Mbit/s)", title="Throughput along the flight")
    a1.legend()
    a1.grid(True)
    rows = [r for r in results["rows"] if r["seed"] == 0]
    a2.semilogx([r["samples"] for r in rows], [r["same_best_pair_pct"] for r in rows], "o-", label="same best pair")
    a2.semilogx([r["samples"] for r in rows], [r["ref_pair_in_top3_pct"] for r in rows], "s-",
                label="ref. pair in top 3")
    a2.set(xlabel="samples per source", ylabel="% of positions", title="Agreement with 1e6 samples")
    a2.grid(True)
    a2.legend()
    fig.tight_layout()
    fig.savefig(OUT / "radio-accuracy.png", dpi=100)


def write(results: dict, name: str) -> None:
    OUT.mkdir(exist_ok=True)
    (OUT / f"{name}.json").write_text(json.dumps(results, indent=2) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    o = sub.add_parser("overhead")
    o.add_argument("--steps", type=int, default=5)
    o.add_argument("--samples", type=int, default=10**6)
    a = sub.add_parser("accuracy")
    a.add_argument("--spacing", type=float, default=10.0)
    args = ap.parse_args()
    {"overhead": overhead, "accuracy": accuracy}[args.what](args)


if __name__ == "__main__":
    sys.exit(main())
