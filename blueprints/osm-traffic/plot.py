"""Throughput per UE against time, with blockage events marked, from a run of
blueprints/osm-traffic (or any run with ``sionna-traffic-link``).

    .venv/bin/python blueprints/osm-traffic/plot.py RUN_DIR [--out throughput.png]

A marker on a UE's curve shows a step in which the straight Tx-Rx line was blocked
(``blocker`` of ``communications.link``): a red cross for a vehicle or a person of the
traffic (the blocker's id is written on the first step of each event), a grey dot for a
building or other static geometry. The lower panel counts the vehicles and persons in
the scene.
"""

from __future__ import annotations

import argparse
import pathlib
import sys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=pathlib.Path)
    ap.add_argument("--out", type=pathlib.Path, default=None, help="default RUN/throughput-blockage.png")
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import caviar

    log = caviar.load_run(args.run)
    link = log.topic("communications.link").sort("time")
    thr = log.topic("communications.throughput").sort("time")
    traffic = log.topic("3D.mobility.traffic").sort("time")
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(11, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    for ue in sorted(set(thr["UE_Id"])):
        t = thr.filter(thr["UE_Id"] == ue)
        (line,) = ax.plot(t["time"], t["throughput"], label=ue, lw=1.5)
        rows = link.filter(link["UE_Id"] == ue)
        mbps = dict(zip(t["time"], t["throughput"], strict=True))
        prev = None
        for r in rows.iter_rows(named=True):
            b = r["blocker"]
            y = mbps.get(r["time"], 0.0)
            if b == "scene":
                ax.plot(r["time"], y, "o", ms=3, color="0.6", zorder=3)
            elif b is not None:
                ax.plot(r["time"], y, "x", ms=8, mew=2, color="red", zorder=4)
                if b != prev:
                    ax.annotate(b, (r["time"], y), textcoords="offset points", xytext=(3, 6), fontsize=7,
                                color="red")
            prev = b
    ax.plot([], [], "x", color="red", mew=2, label="LOS blocked by traffic")
    ax.plot([], [], "o", color="0.6", ms=3, label="LOS blocked by a building")
    ax.set(ylabel="throughput (Mbit/s)", title=f"Throughput per UE, {args.run.name}")
    ax.grid(True)
    ax.legend(fontsize=8, ncol=2)
    ax2.plot(traffic["time"], traffic["vehicles"], label="vehicles")
    ax2.plot(traffic["time"], traffic["persons"], label="pedestrians")
    ax2.set(xlabel="virtual time (s)", ylabel="in the scene")
    ax2.grid(True)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    out = args.out or args.run / "throughput-blockage.png"
    fig.savefig(out, dpi=110)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
