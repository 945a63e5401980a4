"""Issue #18 "Faster steps": each fast path against today's path, measured in the same
run (the old paths stay selectable: camera/detector ``batch = false``, sionna-link
without ``lookahead``).

    .venv/bin/python benches/bench_perf_steps.py [--sar-duration 10] [--samples 1000000] [--reps 5]

* ``camera_50uav``: 50 nadir views, one ``mi.render`` each vs ``render_many`` (interleaved, median of reps);
* ``detector_50uav``: 50 received images, per image on the plugin's default thread pool vs ``detect_many`` in
  two batches per thread on the same pool;
* ``raytrace_{1,10}uav``: one solve at ``--samples``: the bare Sionna calls of today's ``RadioScene.solve``
  (PathSolver + CFR) vs ``RadioScene.solve`` (with overflow detection), and where the time goes
  (Dr.Jit kernel execution, codegen, backend compile, CFR, post-processing);
* ``sar{D}_{1,10}uav_tp_tv``: wall/virtual time of bench_scaling's SAR loop (camera, sionna-link, image link,
  detector; no rescue stops) for ``--sar-duration`` virtual seconds: today's modules vs batched camera and
  detector + look-ahead ray tracing (waypoint-flight ``forecast_steps``, sionna-link ``lookahead``, which needs
  ``uav_mesh = false``); the accuracy effect (best pair, throughput) of the new run against the old one, step by
  step, as bench_radio's ``accuracy`` compares sample counts.

Writes docs/results/perf-steps.json and docs/results/perf-steps.png.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.rt import configure_drjit

configure_drjit()

from bench_common import accuracy_summary, interleaved, machine  # noqa: E402, F401 (machine: bench_realtime)
from perf_runs import ISSUE_24_FILED_AT, bench_main_job, bench_sar, bench_traffic_step, radio_gains  # noqa: E402, F401

OUT = pathlib.Path("docs/results")
ROUTE = "central_park_path0_scene.csv"


def views(n: int) -> list[np.ndarray]:
    """n UAVs spread along the route at 7-12 m (the SAR altitudes), half over targets."""
    from caviar_plugins.vision.camera import default_targets

    rng = np.random.default_rng(0)
    path = Path(read_waypoints(DATA / ROUTE))
    targets = np.array(default_targets())
    out = []
    for i in range(n):
        xy = targets[i % len(targets)] + rng.normal(0, 2.5, 2) if i % 2 == 0 else \
            path.at(rng.uniform(0, path.length))[:2]
        out.append(np.r_[xy, rng.uniform(7.0, 12.0)])
    return out


def bench_vision(reps: int) -> dict:
    from caviar_plugins.vision import VisualConfig, VisualScene, packet_loss
    from caviar_plugins.vision.person_detector import builtin_model

    visual = VisualScene(VisualConfig(), seed=1)
    pos = views(50)
    visual.render(pos[0])
    visual.render_many(pos)  # kernels compiled, ray cache filled
    same = all(np.array_equal(a[0], visual.render(p)) for a, p in zip(visual.render_many(pos), pos, strict=True))
    old_s, new_s = interleaved(lambda: [visual.render(p) for p in pos], lambda: visual.render_many(pos), reps)
    out = {"camera_50uav": {"old_s": old_s, "new_s": new_s, "ratio": new_s / old_s, "images_identical": same}}
    print(f"camera, 50 UAVs: {old_s:.3f} s -> {new_s:.3f} s ({new_s / old_s:.2f}x), identical: {same}", flush=True)

    rng = np.random.default_rng(1)
    images = [packet_loss(im, rate, rng) for (im, _), rate in
              zip(visual.render_many(pos), [0.0, 0.0, 0.01, 0.25, 0.5] * 10, strict=True)]
    det = builtin_model()
    pool = ThreadPoolExecutor(os.cpu_count() or 1)  # the plugin's default (workers = 0)
    chunks = 2 * (os.cpu_count() or 1)  # the plugin's default: two batches per thread
    same = list(pool.map(det.detect, images)) == det.detect_many(images, pool=pool, chunks=chunks)
    old_s, new_s = interleaved(lambda: list(pool.map(det.detect, images)),
                               lambda: det.detect_many(images, pool=pool, chunks=chunks), reps)
    pool.shutdown()
    out["detector_50uav"] = {"old_s": old_s, "new_s": new_s, "ratio": new_s / old_s, "detections_identical": same}
    print(f"detector, 50 UAVs: {old_s:.3f} s -> {new_s:.3f} s ({new_s / old_s:.2f}x), identical: {same}",
          flush=True)
    return out



def bench_solve(n_rx: int, samples: int, reps: int) -> dict:
    """One solve of a static scene (``uav_mesh = false``): Sionna's PathSolver + CFR as
    today's RadioScene.solve called them, against RadioScene.solve with the shoot cache;
    and both against a reference whose specular-chain table is 8x larger (Sionna sizes it
    max(max_num_paths_per_src, 1e6) and drops chains that collide in it)."""
    import drjit as dr

    from caviar_plugins.radio import RadioConfig, RadioScene
    from caviar_plugins.rt.settings import with_raytracing

    path = Path(read_waypoints(DATA / ROUTE))
    starts = np.linspace(0, path.length * 0.9, n_rx)
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, uav_mesh=False), seed=0)
    from caviar_plugins.rt.scene import sionna_rt

    sionna_solver = sionna_rt().PathSolver()  # Sionna's own candidate generator, no cache
    c = radio.cfg
    k = [0]

    def move():
        k[0] += 1
        radio.place({f"uav{i + 1}": path.at(s + 2.5 * k[0]) for i, s in enumerate(starts)})

    def bare(table: int = c.max_num_paths_per_src, seed: int = radio.seed):
        # today's RadioScene.solve: the Sionna calls, then numpy
        paths = sionna_solver(radio.scene, max_depth=c.max_depth, samples_per_src=c.samples_per_src,
                              synthetic_array=True, los=c.los, specular_reflection=c.specular_reflection,
                              diffuse_reflection=c.diffuse_reflection, refraction=c.refraction,
                              diffraction=c.diffraction, seed=seed, max_num_paths_per_src=table)
        return paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")

    def old():
        move()
        bare()

    def new():
        move()
        radio.solve()

    new()
    new()  # the first solve of a geometry runs Sionna's loop, the second records the bounces
    bare()  # compiled
    old_s, new_s = interleaved(old, new, reps)
    # Accuracy: the same positions through Sionna's loop (old), the cache (new) and Sionna's
    # loop on another seed (the Monte Carlo noise), each against a reference: Sionna's loop
    # with an 8x larger specular-chain table.
    labels = ("old", "new", "other_seed")
    errors: dict[str, list] = {k: [] for k in labels}
    same: dict[str, list] = {k: [] for k in labels}
    for _ in range(max(2, 8 // n_rx)):
        move()
        links = radio.solve()
        ref_h = bare(8 * c.max_num_paths_per_src)[:, :, 0, :, 0, 0]
        old_h = bare()[:, :, 0, :, 0, 0]
        seed_h = bare(8 * c.max_num_paths_per_src, radio.seed + 1)[:, :, 0, :, 0, 0]
        for i, key in enumerate(links):
            ref_gain = np.mean(np.abs(ref_h[i]) ** 2)
            ref_best = np.argmax(radio_gains(radio, ref_h[i]))
            for label, h in zip(labels, (old_h[i], links[key].h, seed_h[i]), strict=True):
                errors[label].append(abs(10 * np.log10(np.mean(np.abs(h) ** 2) / ref_gain)))
                same[label].append(int(np.argmax(radio_gains(radio, h)) == ref_best))
    accuracy = accuracy_summary(errors, same)
    accuracy["links"] = len(errors["new"])
    accuracy["reference"] = ("Sionna's loop with max_num_paths_per_src = 8e6 (8x the specular-chain table: fewer "
                             "hash collisions); other_seed = the same on solver seed + 1: the Monte Carlo noise")
    # Where a solve's time goes.
    move()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    t0 = time.perf_counter()
    radio.solve()
    t1 = time.perf_counter()
    hist = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    ms = lambda key: sum((h.get(key) or 0.0) for h in hist) / 1e3  # noqa: E731
    biggest = max((h.get("execution_time") or 0.0) for h in hist) / 1e3
    breakdown = {"solve_s": t1 - t0, "kernel_exec_s": ms("execution_time"), "largest_kernel_s": biggest,
                 "codegen_s": ms("codegen_time"), "backend_compile_s": ms("backend_compile_time"),
                 "kernels": len(hist), "paths_dropped": radio.paths_dropped(),
                 "served_from_cache": radio.shoot_cache.connects if radio.shoot_cache else 0}
    print(f"solve, {n_rx} UAV(s), {samples:.0e} samples: {old_s:.2f} s -> {new_s:.2f} s ({new_s / old_s:.2f}x); "
          f"{breakdown}; {accuracy}", flush=True)
    return {"old_s": old_s, "new_s": new_s, "ratio": new_s / old_s, "breakdown": breakdown, "accuracy": accuracy}


def bench_moving_body(samples: int, positions: int) -> dict:
    """One solve with a moving UAV body (``uav_mesh = true``, 1 UAV along the SAR route):
    Sionna's loop every step (``cache_moving_bodies = false``, today's default until #24) vs
    the shoot cache with the body on top (``cache_moving_bodies = true``), alternating at the
    same positions; both, and Sionna's loop on the next seed, against Sionna's loop with an
    8x larger specular-chain table at the same positions (bodies where they are)."""
    from caviar_plugins.radio import RadioConfig, RadioScene
    from caviar_plugins.rt.settings import with_raytracing

    path = Path(read_waypoints(DATA / ROUTE))
    new = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, cache_moving_bodies=True), seed=0)
    old = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, cache_moving_bodies=False), seed=0)
    from caviar_plugins.rt.scene import sionna_rt

    sionna_solver = sionna_rt().PathSolver()
    c = new.cfg

    def reference(seed: int) -> np.ndarray:
        paths = sionna_solver(new.scene, max_depth=c.max_depth, samples_per_src=c.samples_per_src,
                              synthetic_array=True, los=c.los, specular_reflection=c.specular_reflection,
                              diffuse_reflection=c.diffuse_reflection, refraction=c.refraction,
                              diffraction=c.diffraction, seed=seed, max_num_paths_per_src=8 * c.max_num_paths_per_src)
        return paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")[0, :, 0, :, 0, 0]

    times: dict[str, list] = {"old": [], "new": []}
    labels = ("old", "new", "other_seed")
    errors: dict[str, list] = {k: [] for k in labels}
    same: dict[str, list] = {k: [] for k in labels}
    for s in np.linspace(0, path.length * 0.95, positions):
        pos = {"uav1": path.at(s)}
        h = {}
        for label, radio in (("old", old), ("new", new)):
            radio.place(pos)
            t0 = time.perf_counter()
            h[label] = radio.solve()["uav1"].h
            times[label].append(time.perf_counter() - t0)
        ref_h = reference(new.seed)
        h["other_seed"] = reference(new.seed + 1)
        ref_gain = np.mean(np.abs(ref_h) ** 2)
        ref_best = np.argmax(radio_gains(new, ref_h))
        for label in labels:
            errors[label].append(abs(10 * np.log10(np.mean(np.abs(h[label]) ** 2) / ref_gain)))
            same[label].append(int(np.argmax(radio_gains(new, h[label])) == ref_best))
    # The first solves compile kernels and record the bounces: steady state from the fifth on.
    old_s, new_s = (float(np.median(times[k][4:])) for k in ("old", "new"))
    accuracy = accuracy_summary(errors, same)
    accuracy["links"] = positions
    res = {"old_s": old_s, "new_s": new_s, "ratio": new_s / old_s, "samples": samples,
           "served_from_cache": new.shoot_cache.connects if new.shoot_cache else 0, "solves": positions,
           "first_solves_s": {k: [round(x, 3) for x in v[:4]] for k, v in times.items()}, "accuracy": accuracy}
    print(f"moving body, {samples:.0e} samples: {old_s:.3f} s -> {new_s:.3f} s ({new_s / old_s:.2f}x); {accuracy}",
          flush=True)
    return res


RATIO_TARGETS = {"raytrace_1uav": 0.6, "raytrace_10uav": 0.6, "camera_50uav": 0.3, "detector_50uav": 0.3,
                 "main_job": 0.3, "solve_moving_body": 0.25, "traffic50_step": 0.35}
"""The issues' targets on the ratios (#18, #24); the SAR items' targets are on T_p/T_v itself."""


def plot(results: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [k for k, v in results["ratios"].items() if v is not None]
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.bar(names, [results["ratios"][k] for k in names], color="tab:blue")
    ax.axhline(1.0, color="k", lw=0.8)
    targets = [(i, RATIO_TARGETS[k]) for i, k in enumerate(names) if k in RATIO_TARGETS]
    ax.scatter([i for i, _ in targets], [t for _, t in targets], marker="_", s=900, color="tab:red", zorder=3,
               label="target (ratio)")
    machines = {v.get("machine", "").split(",")[0] for v in results["absolute"].values()
                if isinstance(v, dict) and "ratio" in v}
    ax.set(ylabel="new / old time, same run",
           title="Faster steps, #18 and #24 (lower is better); " + "; ".join(sorted(m for m in machines if m)))
    for i, k in enumerate(names):
        ax.text(i + 0.42, results["ratios"][k], f"{results['ratios'][k]:.2f}", ha="right", va="bottom",
                fontsize=8)
    ax.legend(loc="upper left", fontsize=8)
    plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def moving(args, absolute: dict, ratios: dict, reasons: dict) -> None:
    """The moving-body solve: at the SAR blueprint's 3e5 samples the target's item
    (``solve_moving_body``); at another count an item of its own beside it."""
    if "moving" in args.skip:
        reasons["solve_moving_body"] = "skipped in this run (--skip moving)"
    elif args.moving_samples == 300_000:
        absolute["solve_moving_body"] = bench_moving_body(args.moving_samples, args.moving_positions)
        ratios["solve_moving_body"] = absolute["solve_moving_body"]["ratio"]
    else:
        key = f"solve_moving_body_{args.moving_samples:.0e}_samples".replace("+0", "")
        absolute[key] = bench_moving_body(args.moving_samples, args.moving_positions)


def runs(args, work: pathlib.Path, absolute: dict, ratios: dict, reasons: dict) -> None:
    """The items that run whole blueprints (main job, traffic, SAR), in ``work``."""
    if "main" not in args.skip:
        absolute["main_job"] = bench_main_job(work, args.main_old_rev)
        ratios["main_job"] = absolute["main_job"]["ratio"]
    else:
        reasons["main_job"] = "skipped in this run (--skip main)"
    if "traffic" not in args.skip:
        absolute["traffic50_step"] = bench_traffic_step(work, args.traffic_steps, reps=args.traffic_reps,
                                                         old_rev=args.main_old_rev)
        ratios["traffic50_step"] = absolute["traffic50_step"]["ratio"]
    else:
        reasons["traffic50_step"] = "skipped in this run (--skip traffic)"
    for n, forecast in ((1, args.forecast_1), (10, args.forecast_10)):
        key = f"sar60_{n}uav_tp_tv"
        if f"sar{n}" in args.skip:
            reasons[key] = f"skipped in this run (--skip sar{n}): not enough time on the shared machine"
            continue
        if key in absolute:
            absolute.setdefault("earlier_runs", {}).setdefault(key, []).append(absolute[key])
        absolute[key] = bench_sar(n, args.sar_duration, args.samples, forecast, work)
        ratios[key] = absolute[key]["ratio"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=10**6)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--solve-reps", type=int, default=3)
    ap.add_argument("--sar-duration", type=float, default=10.0)
    ap.add_argument("--forecast-1", type=int, default=9, help="look-ahead steps with 1 UAV")
    ap.add_argument("--forecast-10", type=int, default=2, help="look-ahead steps with 10 UAVs")
    ap.add_argument("--skip", nargs="*", default=[],
                    choices=["vision", "solve", "sar1", "sar10", "moving", "main", "traffic"])
    ap.add_argument("--traffic-steps", type=int, default=30, help="steps of the osm-traffic runs")
    ap.add_argument("--traffic-reps", type=int, default=4, help="osm-traffic runs per variant, in turn")
    ap.add_argument("--main-old-rev", default=ISSUE_24_FILED_AT,
                    help="the commit whose plugins run the main job's old variant")
    ap.add_argument("--moving-positions", type=int, default=30, help="positions of the moving-body solve")
    ap.add_argument("--moving-samples", type=int, default=300_000,
                    help="samples of the moving-body solve (the SAR blueprint's: 3e5); another count is recorded "
                         "as solve_moving_body_<count>_samples, beside the target's item")
    ap.add_argument("--merge", action="store_true",
                    help="keep the items of docs/results/perf-steps.json that this run skips")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    absolute: dict = {}
    reasons: dict = {}
    ratios: dict = {k: None for k in ("raytrace_1uav", "raytrace_10uav", "sar60_1uav_tp_tv", "sar60_10uav_tp_tv",
                                      "camera_50uav", "detector_50uav", "main_job", "solve_moving_body",
                                      "traffic50_step")}
    if args.merge and (OUT / "perf-steps.json").exists():
        old = json.loads((OUT / "perf-steps.json").read_text())
        ratios.update({k: v for k, v in old["ratios"].items() if v is not None})
        for item in old["absolute"].values():  # each kept item names the machine it was measured on
            if isinstance(item, dict) and "ratio" in item:
                item.setdefault("machine", old.get("machine"))
        absolute.update(old["absolute"])
    if "vision" not in args.skip:
        for k in ("camera_50uav", "detector_50uav"):  # a merged earlier measurement stays on record
            if k in absolute:
                absolute.setdefault("earlier_runs", {}).setdefault(k, []).append(absolute[k])
        absolute.update(bench_vision(args.reps))
        ratios["camera_50uav"] = absolute["camera_50uav"]["ratio"]
        ratios["detector_50uav"] = absolute["detector_50uav"]["ratio"]
    else:
        reasons["camera_50uav"] = reasons["detector_50uav"] = "skipped in this run (--skip vision)"
    if "solve" not in args.skip:
        for n in (1, 10):
            absolute[f"raytrace_{n}uav"] = bench_solve(n, args.samples, args.solve_reps)
            ratios[f"raytrace_{n}uav"] = absolute[f"raytrace_{n}uav"]["ratio"]
    else:
        reasons["raytrace_1uav"] = reasons["raytrace_10uav"] = "skipped in this run (--skip solve)"
    moving(args, absolute, ratios, reasons)
    with tempfile.TemporaryDirectory(prefix="perf-steps-") as tmp:
        runs(args, pathlib.Path(tmp), absolute, ratios, reasons)
    here = machine()
    for item in absolute.values():  # this run's items (the kept ones name theirs already)
        if isinstance(item, dict) and "ratio" in item:
            item.setdefault("machine", here)
    results = {
        "ratios": ratios, "absolute": absolute, "machine": here,
        "missing": {k: reasons.get(k, "not measured") for k, v in ratios.items() if v is None},
        "notes": {
            "ratios": "new time / old time, measured in the same run (interleaved for camera, detector, solve).",
            "machine": "the machine of this run; each item's own \"machine\" says where it was measured (with "
                       "--merge, items of earlier runs are kept).",
            "sar": f"The sar60_* items ran {args.sar_duration:g} s of virtual time at Ts = 0.5 s, "
                   f"{args.samples:.0e} samples per source; the first step's kernel compilation is included in "
                   "both runs. Ratio of T_p/T_v (wall / virtual time). The old runs trace every step with the "
                   "UAV bodies (the default); the new ones need uav_mesh = false (look-ahead and the shoot "
                   "cache), so accuracy_vs_old measures the bodies' effect.",
            "raytrace": "One solve of a static scene (uav_mesh = false): the old path is Sionna's PathSolver + "
                        "CFR as RadioScene.solve called them; the new one is RadioScene.solve served by the shoot "
                        "cache (bounces recorded once per geometry, receivers' visibility traced per solve). With "
                        "moving UAV bodies and cache_moving_bodies = false every solve runs Sionna's loop. "
                        "accuracy: path gain and best pair of both against Sionna's loop with an 8x larger "
                        "specular-chain table.",
            "moving": "solve_moving_body: 1 UAV with its body along the SAR route, Sionna's loop every step vs "
                      "the shoot cache with the body on top (median of the solves after the fourth); "
                      "main_job: the SAR blueprint to the end of its mission, whole wall time, old then new; old = the "
                      f"plugins at {args.main_old_rev} (before issue #24), with this checkout's Rust core; "
                      "modules_s: each module's seconds in the steps where the UAV moved and where it hovered.",
            "traffic": "traffic50_step: the osm-traffic blueprint (about 50 vehicles and 20 persons moving, 6 "
                       f"receivers, 1e5 samples); old = the plugins at {args.main_old_rev} (before #24: Sionna's "
                       "loop every step), loop = this checkout with shoot_cache = false (Sionna's loop, the "
                       "link's other work as now), new = the default (the pools' boxes as moving objects of the "
                       "shoot cache), runs in turn; a step = the sum of its modules' wall times, median after the "
                       "first ten (the vehicles depart over the first 10 s). floor: the shoot cache without the "
                       "traffic boxes (the UAV's body still moving). "
                       "accuracy: the new run's positions replayed into the link, each connected receiver "
                       "against Sionna's loop with an 8x table on the same geometry.",
        },
    }
    (OUT / "perf-steps.json").write_text(json.dumps(results, indent=2) + "\n")
    plot(results, OUT / "perf-steps.png")
    print(json.dumps(results["ratios"], indent=2))


if __name__ == "__main__":
    main()
