"""Benchmark of the radio network (issue #23): 21 cells (7 sites × 3 sectors) and 100 UEs
(60 cars, 30 pedestrians, 10 UAVs) in the osm-city scene, 0.5 ms slots, 0.1 s steps.

Runs of the same virtual time, in one process:

- ``sys only``: the channels are traced once and held; every step runs the
  measurements, mobility management and the Sionna SYS slots (once slot by slot, the
  baseline, and once ``--harq-processes`` slots per call);
- ``with rt``: the same, and every UE's channels are ray traced again every
  ``--refresh`` seconds of virtual time (all sites in one solve).

Writes ``docs/results/network.json`` with T_p/T_v of both, the share of a step the SYS
layer takes, and the machine. Not a test: it takes minutes.

    .venv/bin/python benches/bench_network.py [--seconds 2.0] [--refresh 1.0]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

from bench_perf_steps import machine
from caviar_plugins.network.cells import parse_sites, rsrp_dbm, rx_power_dbm, sinr_db
from caviar_plugins.network.handover import HandoverSettings, MobilityManager
from caviar_plugins.network.raytraced import SiteTracer, TraceSettings
from caviar_plugins.radio.link_level import LinkLevel, LinkSettings

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "network.json"
SCENE = ROOT / "blueprints" / "osm-city" / "scene" / "scene.xml"
TS, SCS, NUM_PRB = 0.1, 30e3, 51


def sites() -> list[dict]:
    """7 sites: a centre and a ring of 6 at 280 m, masts 35 m high, 3 sectors each."""
    out = [{"name": "s0", "position": [0.0, 0.0, 35.0]}]
    for k in range(6):
        a = np.radians(60 * k + 30)
        out.append({"name": f"s{k + 1}", "position": [280 * np.cos(a), 280 * np.sin(a), 35.0]})
    for s in out:
        s["azimuths_deg"], s["downtilt_deg"] = [30.0, 150.0, 270.0], 6.0
    return out


def ues(rng: np.random.Generator):
    """100 UEs: start positions and velocities (cars 10 m/s, pedestrians 1.4 m/s, UAVs 8 m/s
    at 40 m)."""
    kinds = ["car"] * 60 + ["pedestrian"] * 30 + ["uav"] * 10
    speed = {"car": 10.0, "pedestrian": 1.4, "uav": 8.0}
    pos = np.column_stack([rng.uniform(-380, 380, 100), rng.uniform(-380, 380, 100),
                           [40.0 if k == "uav" else 1.5 for k in kinds]])
    heading = rng.uniform(0, 2 * np.pi, 100)
    vel = np.column_stack([np.cos(heading), np.sin(heading), np.zeros(100)]) * [[speed[k]] for k in kinds]
    return kinds, pos, vel


def run(seconds: float, refresh: float | None, tracer: SiteTracer, cells, pos0, vel, initial,
        processes: int) -> dict:
    link = LinkLevel(LinkSettings(num_prb=NUM_PRB, subcarrier_spacing_hz=SCS, harq_processes=processes),
                     len(cells), seed=1)
    mm = MobilityManager(HandoverSettings(), [c.name for c in cells])
    slots = round(TS / link.s.slot_s)
    gains, t_rt, t_sys, last_sinr = initial, 0.0, 0.0, {}
    steps = round(seconds / TS)
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * TS
        pos = pos0 + vel * t
        if refresh is not None and k and k % round(refresh / TS) == 0:
            a = time.perf_counter()
            gains = tracer.gains_db(pos)
            t_rt += time.perf_counter() - a
        a = time.perf_counter()
        rx = rx_power_dbm(cells, gains)
        rsrp = rsrp_dbm(cells, rx, [NUM_PRB] * len(cells))
        for u in range(len(pos)):
            mm.update(t, str(u), list(rsrp[u]), last_sinr.get(u))
        serving = np.array([mm.serving(str(u)) for u in range(len(pos))])
        sinr = sinr_db(cells, rx, serving, 7.0)
        link.run(np.tile(sinr, (slots, 1)), serving)
        last_sinr = {u: float(s) for u, s in enumerate(sinr) if serving[u] >= 0}
        t_sys += time.perf_counter() - a
    wall = time.perf_counter() - t0
    return {"harq_processes": processes, "virtual_s": seconds, "wall_s": round(wall, 3),
            "tp_tv": round(wall / seconds, 3),
            "rt_s": round(t_rt, 3), "sys_s": round(t_sys, 3), "slots": steps * slots,
            "ms_per_slot": round(1e3 * t_sys / (steps * slots), 3), "covered_ues": int((serving >= 0).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=2.0, help="virtual seconds per run")
    ap.add_argument("--refresh", type=float, default=1.0, help="ray-tracing refresh, virtual seconds")
    ap.add_argument("--samples", type=int, default=20000, help="rays per site")
    ap.add_argument("--harq-processes", type=int, default=8, help="slots per call (1: the slot-by-slot baseline)")
    args = ap.parse_args()
    cells = parse_sites(sites(), {"tx_power_dbm": 43.0, "carrier_hz": 3.5e9, "bandwidth_hz": 20e6,
                                  "array": [4, 4]})
    kinds, pos0, vel = ues(np.random.default_rng(7))
    tracer = SiteTracer(TraceSettings(scene=str(SCENE), max_depth=2, samples_per_src=args.samples), cells, seed=1)
    a = time.perf_counter()
    initial = tracer.gains_db(pos0)
    first_trace = time.perf_counter() - a
    print(f"first trace (kernel compilation included): {first_trace:.2f} s", flush=True)
    d = args.harq_processes
    baseline = run(args.seconds, None, tracer, cells, pos0, vel, initial, 1)
    print("sys only, slot by slot", baseline, flush=True)
    sys_only = run(args.seconds, None, tracer, cells, pos0, vel, initial, d)
    print(f"sys only, {d} HARQ processes per call", sys_only, flush=True)
    with_rt = run(args.seconds, args.refresh, tracer, cells, pos0, vel, initial, d)
    print("with rt", with_rt, flush=True)
    result = {
        "cells": len(cells), "ues": len(pos0), "ue_types": {k: kinds.count(k) for k in sorted(set(kinds))},
        "slot_s": 1e-3 * 15e3 / SCS, "step_s": TS, "rt_refresh_s": args.refresh, "samples_per_src": args.samples,
        "harq_processes": d, "tp_tv_sys_only": sys_only["tp_tv"], "tp_tv_with_rt": with_rt["tp_tv"],
        "tp_tv_sys_only_slot_by_slot": baseline["tp_tv"],
        "speedup_of_harq_batching": round(baseline["wall_s"] / sys_only["wall_s"], 2),
        "sys_share_of_step": round(with_rt["sys_s"] / with_rt["wall_s"], 3),
        "rt_share_of_step": round(with_rt["rt_s"] / with_rt["wall_s"], 3),
        "targets": {"tp_tv_sys_only": 1.0, "tp_tv_with_rt": 3.0},
        "runs": {"sys_only_slot_by_slot": baseline, "sys_only": sys_only, "with_rt": with_rt},
        "first_trace_s": round(first_trace, 2),
        "machine": machine(),
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("tp_tv_sys_only", "tp_tv_with_rt", "sys_share_of_step")}))


if __name__ == "__main__":
    main()
