"""The LiDAR's speed (issue #43, part 1): one 32-channel sweep of 1,800 × 32 rays in the
osm-city scene (252 buildings of central Helsinki) with 20 car-sized boxes in it, from a UAV
30 m above the street. Target: at most 20 ms a sweep on the 2-core machine.

Measured in the same run, as the baseline: the bare Mitsuba intersection of the same rays
(one ``ray_intersect``, no noise, labels or intensity): the floor of a sweep. Writes
``docs/results/lidar.json``.

    .venv/bin/python benches/bench_lidar.py
"""

from __future__ import annotations

import json
import pathlib
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from bench_common import machine  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENE = ROOT / "blueprints" / "osm-city" / "scene" / "scene.xml"
REPS = 50


def main() -> dict:
    import sionna.rt as rt

    from caviar_plugins.lidar import Caster, LidarSettings
    from caviar_plugins.rt.drjit_setup import aligned_array, jit
    from caviar_plugins.rt.scatterers import Body, ScattererPool
    from caviar_plugins.rt.scene import load_scene

    dr, mi = jit()
    scene = load_scene(str(SCENE), merge_shapes=False)
    pool = ScattererPool(scene, {"vehicle": 32}, {"vehicle": rt.ITURadioMaterial("bench-vehicle", "metal", 0.01)},
                         prefix="bench")
    rng = np.random.default_rng(1)
    pool.update([Body(f"car{i}", "vehicle", (float(x), float(y), 0.0), float(h), (4.5, 1.8, 1.5))
                 for i, (x, y, h) in enumerate(zip(rng.uniform(-60, 60, 20), rng.uniform(-60, 60, 20),
                                                   rng.uniform(0, 6.28, 20), strict=True))])
    settings = LidarSettings()  # 32 channels, 0.2°: 1,800 columns
    caster = Caster(scene, settings, [pool])
    origin = np.array([10.0, 0.0, 30.0])
    origins = origin + np.linspace(0, 1.0, settings.columns)[:, None] * [1.0, 0.0, 0.0]  # 10 m/s for 0.1 s

    d = settings.directions().reshape(-1, 3).astype(np.float32)
    o = np.repeat(origins.astype(np.float32), settings.channels, axis=0)

    def bare():
        ray = mi.Ray3f(mi.Point3f(*(aligned_array(mi.Float, np.ascontiguousarray(o[:, k])) for k in range(3))),
                       mi.Vector3f(*(aligned_array(mi.Float, np.ascontiguousarray(d[:, k])) for k in range(3))))
        ray.maxt = mi.Float(settings.max_range_m)
        si = scene.mi_scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
        t = dr.select(si.is_valid(), si.t, 0.0)
        dr.eval(t)
        return np.array(t)

    for _ in range(5):  # Dr.Jit compiles its kernels once
        bare()
        caster.cast(origins, rng)
    floor, sweep = [], []
    for _ in range(REPS):
        t0 = time.perf_counter()
        bare()
        t1 = time.perf_counter()
        result = caster.cast(origins, rng)
        sweep.append(time.perf_counter() - t1)
        floor.append(t1 - t0)
    out = {
        "machine": machine(),
        "scene": "blueprints/osm-city/scene/scene.xml (252 buildings, 13,598 faces) + 20 car boxes",
        "sweep": {"channels": settings.channels, "columns": settings.columns,
                  "rays": settings.channels * settings.columns, "returns": int(len(result.points)),
                  "objects": result.objects},
        "sweep_ms_median": round(1e3 * statistics.median(sweep), 2),
        "sweep_ms_p90": round(1e3 * float(np.percentile(sweep, 90)), 2),
        "bare_intersection_ms_median": round(1e3 * statistics.median(floor), 2),
        "ratio_sweep_to_bare": round(statistics.median(sweep) / statistics.median(floor), 2),
        "target_ms": 20.0,
        "reps": REPS,
    }
    out["meets_target"] = out["sweep_ms_median"] <= out["target_ms"]
    path = ROOT / "docs" / "results" / "lidar.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
