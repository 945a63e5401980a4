"""Figures of a run with a LiDAR, for ``caviar-core report`` (entry-point group
``caviar.report``): per UE, the last sweep it saved (``save_every``) seen from above and from
the side, coloured by what it hit, and ``lidar.json`` with the sweeps' counts.

    caviar-core report runs/lidar-city-001 --out report/
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.report_figures import pyplot_into, save_figure, save_numbers
from caviar_plugins.schema import LIDAR


def summarize(log) -> dict[str, Any] | None:
    """Per UE: sweeps, rays, returns and drops. None for a run without a LiDAR."""
    sweeps = [m.data for m in log.decoded(f"{LIDAR}.*.sweep")]
    if not sweeps:
        return None
    out: dict[str, Any] = {}
    for ue in sorted({s["UE_Id"] for s in sweeps}):
        mine = [s for s in sweeps if s["UE_Id"] == ue]
        out[ue] = {"sweeps": len(mine), "rays": sum(s["rays"] for s in mine),
                   "returns": sum(s["points"] for s in mine), "dropped": sum(s["dropped"] for s in mine),
                   "objects_seen": sorted({o for s in mine for o in s["objects"]})}
    return {"ues": out}


def figures(log, out: pathlib.Path) -> list[pathlib.Path]:
    summary = summarize(log)
    if summary is None:
        return []
    plt = pyplot_into(out)
    paths = []
    saved: dict[str, pathlib.Path] = {}
    for m in log.decoded(f"{LIDAR}.*.file"):
        saved[m.topic.split(".")[2]] = pathlib.Path(m.data)  # (an artifact: its path in the run directory)
    for ue, path in sorted(saved.items()):
        data = np.load(path)
        points, objects = data["points"], [str(o) for o in data["objects"]]
        origin = data["origin"]
        fig, (ax, bx) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [1.2, 1]})
        obj = points[:, 5].astype(int)
        for k, name in enumerate(objects):
            sel = obj == k
            ax.scatter(points[sel, 0], points[sel, 1], s=0.3, color=f"C{k % 10}", label=f"{name} ({sel.sum()})")
            bx.scatter(np.hypot(points[sel, 0] - origin[0], points[sel, 1] - origin[1]), points[sel, 2], s=0.3,
                       color=f"C{k % 10}")
        ax.plot(origin[0], origin[1], "k^", ms=8)
        ax.set(xlabel="x (m)", ylabel="y (m)", aspect="equal",
               title=f"{ue}: sweep at t = {float(data['time']):g} s, {len(points)} returns")
        ax.legend(markerscale=15, fontsize=7, loc="upper right")
        bx.set(xlabel="horizontal distance from the sensor (m)", ylabel="z (m)", title="side view")
        for axis in (ax, bx):
            axis.grid(True, alpha=0.4)
        paths.append(save_figure(fig, out / f"lidar-{ue}.png"))
    return [*paths, save_numbers(summary, out / "lidar.json")]
