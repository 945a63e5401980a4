"""Moving scatterers in the ray tracer: per-step cost against the number of moving
objects, and the share of it spent moving meshes.

On the osm-city scene (Helsinki, 13,598 faces) with the osm-traffic blueprint's rooftop
base station (8x8) and 6 receivers (2x2) near street level, a pool of N car-sized metal
boxes (N = 0, 10, 50, 200) is added once; each step every box moves (10 m/s along its
heading, new velocity), then one path solve runs (depth 5, specular + diffuse
reflection, refraction, diffraction, 1e5 samples). Boxes start at uniform random points of
the 500 m square around the base station (some inside buildings: the tracer does not
care). Per N: scene load, pool creation (one ``scene.edit``), the first step (kernel
compilation), then STEPS measured steps: mesh update (vertex rewrite + one
``params.update()``), solve, and how many kernels Dr.Jit had to compile in that step
(0 = nothing recompiled). The pool's boxes are one mesh (ScattererPool: one shape in the
solver's virtual calls however many boxes); until 2026-11-26 each was a mesh of its own, and
this bench then also timed Sionna's per-object ``SceneObject.position`` setter for the same N
(0.35, 1.7 and 7.4 s for 10, 50 and 200: one BVH rebuild per object).

    .venv/bin/python benches/bench_traffic.py [--steps 5] [--counts 0,10,50,200] [--out docs/results/traffic/bench.json]

With ``--cold COUNTS`` it first runs those counts in a child process whose HOME is an
empty folder, so that Dr.Jit finds no kernel cache (``~/.drjit``) and compiles everything:
the cost of a first run on a fresh machine (stored under ``cold_cache``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCENE = ROOT / "blueprints" / "osm-city" / "scene" / "scene.xml"
TX = [81.0, -41.0, 32.0]


def machine() -> str:
    """The machine as it is (:func:`caviar_plugins.machine.summary`: CPU, GPU, Dr.Jit variant, torch device)."""
    from caviar_plugins.machine import summary

    return summary()


def compiled(dr) -> tuple[int, float, int]:
    """JIT kernels launched since the last call that Dr.Jit had to compile (found in
    neither its memory nor its disk cache ``~/.drjit``): how many, their compile time
    (ms), the largest one's operation count."""
    new = [k for k in dr.kernel_history() if "JIT" in str(k.get("type")) and not k.get("cache_hit")]
    ms = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in new)
    return len(new), ms, max((k.get("operation_count", 0) for k in new), default=0)


def run(n: int, steps: int, seed: int = 0) -> dict:
    import drjit as dr

    from caviar_plugins.radio.scene import RadioConfig, RadioScene
    from caviar_plugins.rt.scatterers import Body, ScattererPool
    from caviar_plugins.rt.scene import itu_material
    from caviar_plugins.rt.settings import with_raytracing

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    radio = RadioScene(with_raytracing(RadioConfig, scene=str(SCENE), tx_position=TX, tx_orientation=[-2.72, 0.1, 0.0],
                                   samples_per_src=100_000, uav_mesh=False, antenna_offset=[0.0, 0.0, 0.0],
                                   shoot_cache=False))  # movers change the geometry: as sionna-traffic-link
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    pool = ScattererPool(radio.scene, {"vehicle": n} if n else {},
                         {"vehicle": itu_material("bench-metal", "metal", thickness=0.01)})
    pool_s = time.perf_counter() - t0
    rx = {f"rx{i}": np.array([TX[0] + rng.uniform(-150, 150), TX[1] + rng.uniform(-150, 150), 1.6])
          for i in range(6)}
    radio.place(rx)
    xy = np.column_stack([TX[0] + rng.uniform(-250, 250, n), TX[1] + rng.uniform(-250, 250, n)])
    yaw = rng.uniform(-np.pi, np.pi, n)

    def bodies(k):
        v = 10.0 * np.column_stack([np.cos(yaw + 0.05 * k), np.sin(yaw + 0.05 * k)])
        p = xy + k * v
        return [Body(f"v{i}", "vehicle", (p[i, 0], p[i, 1], 0.0), yaw[i] + 0.05 * k, (4.5, 1.8, 1.5),
                     (v[i, 0], v[i, 1], 0.0)) for i in range(n)]

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows = []
    for k in range(steps + 1):
        dr.kernel_history()  # clears it
        t0 = time.perf_counter()
        pool.update(bodies(k))
        t1 = time.perf_counter()
        links = radio.solve(force=True)
        t2 = time.perf_counter()
        n_new, ms, ops = compiled(dr)
        rows.append({"update_s": t1 - t0, "solve_s": t2 - t1, "kernels_compiled": n_new, "compile_ms": ms,
                     "largest_compiled_ops": ops, "paths": int(sum(lk.n_paths for lk in links.values()))})
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    steady = rows[1:]
    upd = statistics.median(r["update_s"] for r in steady)
    sol = statistics.median(r["solve_s"] for r in steady)
    out = {"objects": n, "load_s": round(load_s, 3), "pool_edit_s": round(pool_s, 3),
           "first_step_s": round(rows[0]["update_s"] + rows[0]["solve_s"], 3),
           "first_step_kernels_compiled": rows[0]["kernels_compiled"],
           "first_step_compile_ms": round(rows[0]["compile_ms"], 1),
           "first_step_largest_compiled_ops": rows[0]["largest_compiled_ops"],
           "update_s": round(upd, 4), "solve_s": round(sol, 3), "step_s": round(upd + sol, 3),
           "update_share": round(upd / (upd + sol), 4),
           "steady_kernels_compiled": [r["kernels_compiled"] for r in steady],
           "steady_compile_ms": [round(r["compile_ms"], 1) for r in steady],
           "steady_largest_compiled_ops": max(r["largest_compiled_ops"] for r in steady),
           "paths": [r["paths"] for r in rows],
           "steps": [{k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()} for r in rows]}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--cold", default="", help="counts to run first without a kernel cache, e.g. 0,50")
    ap.add_argument("--counts", default="0,10,50,200")
    ap.add_argument("--out", type=pathlib.Path, default=ROOT / "docs" / "results" / "traffic" / "bench.json")
    args = ap.parse_args(argv)
    cold = None
    if args.cold:
        import subprocess
        import tempfile

        with tempfile.TemporaryDirectory() as home:
            out = pathlib.Path(home) / "cold.json"
            subprocess.run([sys.executable, __file__, "--steps", str(args.steps), "--counts", args.cold,
                            "--out", str(out)], env=dict(os.environ, HOME=home), check=True)
            cold = json.loads(out.read_text())["results"]
    from caviar_plugins.rt import configure_drjit

    configure_drjit()
    results = []
    for n in (int(c) for c in args.counts.split(",")):
        r = run(n, args.steps)
        results.append(r)
        print(f"N = {n:4d}: step {r['step_s']:.3f} s = update {r['update_s'] * 1e3:.1f} ms "
              f"({100 * r['update_share']:.1f} %) + solve {r['solve_s']:.3f} s; first step {r['first_step_s']:.2f} s; "
              f"compiled in steady steps: {r['steady_kernels_compiled']} kernels, {r['steady_compile_ms']} ms, "
              f"largest {r['steady_largest_compiled_ops']} ops (first step: {r['first_step_compile_ms']} ms, "
              f"largest {r['first_step_largest_compiled_ops']} ops); paths {r['paths']}", flush=True)
    import mitsuba
    import sionna.rt

    doc = {"machine": machine(), "load_average_1_5_15": list(os.getloadavg()),
           "python": platform.python_version(), "sionna_rt": sionna.rt.__version__,
           "mitsuba": mitsuba.__version__, "scene": str(SCENE.relative_to(ROOT)), "tx": TX, "receivers": 6,
           "solver": {"max_depth": 5, "samples_per_src": 100_000, "diffuse": True, "diffraction": True,
                      "refraction": True},
           "box": "4.5 x 1.8 x 1.5 m, ITU metal, moving 10 m/s", "results": results}
    if cold is not None:
        doc["cold_cache"] = cold
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
