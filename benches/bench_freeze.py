"""Where a solve's time goes, and whether Dr.Jit's function freezing removes it (issue #39,
part 3). Two items, on whatever backend Sionna RT chose (LLVM on a CPU, CUDA on a GPU):

* ``split``: one solve of the SAR route (1e6 samples) with Sionna's loop and with the shoot
  cache, its wall time against Dr.Jit's kernel history: kernel execution, code generation,
  backend compilation and the rest (host: Python, numpy, tracing);
* ``freeze``: cached solves with the connect phase's visibility test (its repeated kernel)
  run through ``@dr.freeze`` or not, interleaved, the links compared.

    .venv/bin/python benches/bench_freeze.py [--uavs 1 10] [--samples 1000000]

Measured on a 2-core AMD EPYC (LLVM) on 2026-11-27, while a CI run shared the machine
(ratios interleaved): 1 UAV, Sionna's loop 3.0 s of which 2.96 s in kernels; the cache
0.36 s: kernels 0.24 s, codegen 9 ms, the rest 0.12 s (the connect phase's numpy and Python).
Freezing the visibility test: 1.03x (1 UAV) and 1.05x (10 UAVs) of the unfrozen time, links
identical: on the CPU tracing is not where the time goes. On the H100 of the GPU notes, 18 of a
solve's 189 ms were kernels: run this there.
"""

import argparse
import statistics
import time

import numpy as np

from caviar_plugins.rt import configure_drjit

configure_drjit()  # before Dr.Jit and Mitsuba are imported
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from caviar_plugins import DATA  # noqa: E402
from caviar_plugins.mobility import Path, read_waypoints  # noqa: E402
from caviar_plugins.radio import RadioConfig, RadioScene  # noqa: E402
from caviar_plugins.rt.drjit_setup import aligned_array  # noqa: E402
from caviar_plugins.rt.settings import with_raytracing  # noqa: E402
from caviar_plugins.rt.shoot_cache import connect  # noqa: E402

original = connect.visibility


@dr.freeze
def _frozen(mi_scene, p, n, tgt_positions, j, t):
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(j))
    si.p, si.n = dr.gather(mi.Point3f, p, j), dr.gather(mi.Normal3f, n, j)
    ray = si.spawn_ray_to(dr.gather(mi.Point3f, tgt_positions, t))
    visible = ~mi_scene.ray_test(ray)
    side = dr.dot(si.n, ray.d) > 0.0
    return visible, side, mi.Vector3f(ray.d)


def frozen_visibility(mi_scene, rec, tgt_positions, rays, targets):
    j, t = aligned_array(mi.UInt, rays.astype(np.uint32)), aligned_array(mi.UInt, targets.astype(np.uint32))
    visible, side, direction = _frozen(mi_scene, rec.p, rec.n, tgt_positions, j, t)
    dr.eval(visible, side, direction)
    return np.asarray(visible, dtype=bool), np.asarray(side, dtype=bool), direction




def split(n_uav: int, samples: int, cache: bool) -> None:
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, uav_mesh=False, shoot_cache=cache), seed=0)
    starts = np.linspace(0.0, 0.9 * route.length, n_uav)
    rows = []
    for k in range(8):
        radio.place({f"u{i}": route.at(s + 0.5 * k) for i, s in enumerate(starts)})
        dr.kernel_history()  # (reading it empties it)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        t0 = time.perf_counter()
        radio.solve(force=True)
        wall = time.perf_counter() - t0
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        run = sum(h.get("execution_time", 0.0) for h in hist) / 1e3
        codegen = sum(h.get("codegen_time", 0.0) for h in hist) / 1e3
        backend = sum(h.get("backend_time", 0.0) for h in hist) / 1e3
        if k >= 3:
            rows.append((wall, run, codegen, backend, len(hist)))
    w, r, c, b, n = (statistics.median(x) for x in zip(*rows, strict=True))
    print(f"{n_uav} UAV(s), {'cache' if cache else 'Sionna loop'}: wall {w*1e3:.0f} ms, kernels run {r*1e3:.0f} ms, "
          f"codegen {c*1e3:.0f} ms, backend compile {b*1e3:.0f} ms, {n:.0f} kernels; host rest {(w-r-c-b)*1e3:.0f} ms")


def freeze(n_uav: int, samples: int) -> None:
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, uav_mesh=False, threads=0,
                                       shoot_cache=True), seed=0)
    starts = np.linspace(0.0, 0.9 * route.length, n_uav)
    times = {"plain": [], "frozen": []}
    same = True
    for k in range(14):
        pos = {f"u{i}": route.at(s + 0.5 * k) for i, s in enumerate(starts)}
        out = {}
        for label in ("plain", "frozen") if k % 2 == 0 else ("frozen", "plain"):
            connect.visibility = frozen_visibility if label == "frozen" else original
            radio.place(pos)
            t0 = time.perf_counter()
            links = radio.solve(force=True)
            dt = time.perf_counter() - t0
            if k >= 4:
                times[label].append(dt)
            out[label] = links
        if k >= 2:
            for key in out["plain"]:
                a, b = out["plain"][key], out["frozen"][key]
                if a.n_paths != b.n_paths or abs(10 * np.log10(a.path_gain / b.path_gain)) > 1e-3:
                    same = False
    connect.visibility = original
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{n_uav} UAV(s), {samples:.0e} samples, cached solves: plain {med['plain']*1e3:.1f} ms, frozen "
          f"{med['frozen']*1e3:.1f} ms, ratio {med['frozen']/med['plain']:.3f}, links same: {same}; "
          f"served from cache {radio.shoot_cache.connects} of {radio.solves}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--uavs", type=int, nargs="+", default=[1, 10])
    ap.add_argument("--samples", type=int, default=1_000_000)
    args = ap.parse_args()
    import sionna.rt  # noqa: F401  (it chooses the variant: CUDA where a GPU is found)

    print(f"Dr.Jit variant: {mi.variant()}", flush=True)
    for n in args.uavs:
        for cache in (False, True):
            split(n, args.samples, cache)
        freeze(n, args.samples)


if __name__ == "__main__":
    main()
