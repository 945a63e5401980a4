"""The ray-tracing refresh of the radio network's channel (issue #53, part 4): one solve of
21 sites (7 sites × 3 sectors, every site a source) to ``n_ue`` UEs on the osm-city scene, timed
first and warm on this machine, with what it would cost on an H200 extrapolated from the H200's
solve figures (not measured there). ``benches/bench_host_overhead.py`` runs it and keeps it with
the host-overhead figures (``rt_refresh``).

    python benches/bench_rt_refresh.py --ues 1000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

H200_SOLVE = {"one_uav_1e6_samples_ms": {"warm": 39, "kernels": 17, "host": 18},
              "ten_uavs_1e6_samples_ms": {"warm": 117, "kernels": 43, "host": 65}}
"""One Sionna RT solve on an H200 (issue #53's figures): 1 UAV and 10 UAVs, 1e6 samples."""


def refresh(n_ue: int, samples: int) -> dict:
    """One ray-tracing refresh of 21 sites × ``n_ue`` UEs (all sites in one solve), warm."""
    from bench_network import SCENE, sites, ues
    from caviar_plugins.network.cells import parse_sites
    from caviar_plugins.network.raytraced import NETWORK_RAYS, SiteTracer

    cells = parse_sites(sites(), {"tx_power_dbm": 43.0, "carrier_hz": 3.5e9, "bandwidth_hz": 20e6, "array": [4, 4]})
    _, pos0, vel = ues(np.random.default_rng(7), n_ue)
    tracer = SiteTracer(str(SCENE), dataclasses.replace(NETWORK_RAYS, max_depth=2, samples_per_src=samples), cells,
                        seed=1)
    a = time.perf_counter()
    tracer.trace(pos0)
    first = time.perf_counter() - a
    times = []
    for k in (1, 2):
        a = time.perf_counter()
        tracer.trace(pos0 + vel * k)
        times.append(time.perf_counter() - a)
    sites_n = len({c.site for c in cells})
    warm = min(times)
    # An H200 solve, from its 1 -> 10 UAV figures read as 1 -> 10 sources of 1e6 samples each: a first
    # source's kernels and host, and each further source's (an upper bound for fewer samples a source).
    one_, ten = H200_SOLVE["one_uav_1e6_samples_ms"], H200_SOLVE["ten_uavs_1e6_samples_ms"]
    kernels = one_["kernels"] + (ten["kernels"] - one_["kernels"]) / 9 * (sites_n - 1)
    host = one_["host"] + (ten["host"] - one_["host"]) / 9 * (sites_n - 1)
    return {"sites": sites_n, "cells": len(cells), "ues": n_ue, "samples_per_src": samples, "solves": 1,
            "first_s": round(first, 2), "warm_s": round(warm, 3),
            "h200_estimate_ms": {"kernels": round(kernels, 1), "host": round(host, 1),
                                 "total": round(kernels + host, 1)},
            "h200_estimate": (f"an extrapolation, not a measurement: the H200 solve figures {H200_SOLVE} read as 1 and "
                              f"10 sources of 1e6 samples, scaled linearly to {sites_n} sources (the sites) of "
                              f"{samples:g} samples, an upper bound on the rays; how the solve grows with {n_ue:,} "
                              "receivers against their one is not in those figures")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ues", type=int, default=1000)
    ap.add_argument("--samples", type=int, default=20000, help="rays per site")
    args = ap.parse_args()
    print(json.dumps(refresh(args.ues, args.samples)))


if __name__ == "__main__":
    main()
