"""Figures of a run with the radio network, for ``caviar-core report`` (entry-point group
``caviar.report``): SINR and throughput CDFs per UE type (downlink, and uplink when the run
has one), the handovers and serving beams on a map and, with a load (``traffic``), the
delay and user-perceived throughput CDFs of files and carried messages, with
``network.json`` holding the numbers the figures show.

    caviar-core report runs/network-city-001 --out report/
"""

from __future__ import annotations

import math
import pathlib
from typing import Any

import numpy as np
import tomllib

from caviar_plugins.report_figures import pyplot_into, save_figure, save_numbers
from caviar_plugins.schema import NETWORK_EVENTS, NETWORK_TRANSFERS, NETWORK_UE, NETWORK_UES, POSITIONS


def ue_rows(log) -> list[tuple[int, dict[str, Any]]]:
    """The run's UE reports, (step, ``network.ue`` report) in order, whether it published them a
    message a UE or as ``network.ues`` tables (``ue_reports = "table"``, read back as the same
    reports)."""
    from caviar_plugins.network.ues import table_rows

    rows = [(m.step, m.data) for m in log.decoded(NETWORK_UE)]
    for m in log.decoded(NETWORK_UES):
        rows += [(m.step, r) for r in table_rows(m.data)]
    return rows


def _cdf(ax, values: dict[str, np.ndarray], xlabel: str) -> None:
    for kind, v in sorted(values.items()):
        v = np.sort(v)
        ax.step(v, np.arange(1, v.size + 1) / v.size, where="post", label=f"{kind} ({v.size})")
    ax.set(xlabel=xlabel, ylabel="CDF", ylim=(0, 1))
    ax.grid(True)
    ax.legend()


def _sites(log) -> list[dict[str, Any]]:
    """The sites of the run's radio-network module(s), from its config: hand-placed, or
    those of its standard layout."""
    from caviar_plugins.network.layout import SECTOR_AZIMUTHS_DEG, LayoutSettings, site_positions

    cfg = tomllib.loads(log.config_text)
    out: list[dict[str, Any]] = []
    for m in cfg.get("modules", {}).values():
        if m.get("plugin") != "radio-network":
            continue
        params = m.get("params", {})
        out += params.get("sites", [])
        if "layout" in params:
            layout = LayoutSettings(**params["layout"])
            out += [{"name": f"S{i}", "position": [float(x), float(y), layout.height_m],
                     "azimuths_deg": list(SECTOR_AZIMUTHS_DEG)} for i, (x, y) in enumerate(site_positions(layout))]
    return out


def _beams(ax, log, track: dict[str, dict[int, tuple[float, float]]], samples: int = 12) -> None:
    """With SSB beams (``network.ue``'s ``beam_azimuth_deg``): from each UE's serving site, its
    serving beam's direction out to the UE's distance, at ``samples`` instants of its track."""
    site = {s["name"]: s["position"][:2] for s in _sites(log)}
    rows = [(step, r) for step, r in ue_rows(log) if r.get("beam_azimuth_deg") is not None]
    drawn = False
    for k, ue in enumerate(sorted({r["UE_Id"] for _, r in rows})):
        mine = [(step, r) for step, r in rows if r["UE_Id"] == ue and step in track.get(ue, {})]
        for step, r in mine[::max(1, len(mine) // samples)]:
            x0, y0 = site[r["serving_cell"].split("/")[0]]
            x, y = track[ue][step]
            reach = math.hypot(x - x0, y - y0)
            az = math.radians(r["beam_azimuth_deg"])
            ax.plot([x0, x0 + reach * math.cos(az)], [y0, y0 + reach * math.sin(az)], color=f"C{k % 10}",
                    lw=0.8, alpha=0.6, label=None if drawn else "serving SSB beam")
            drawn = True


def finite(x: float, digits: int = 3) -> float | None:
    """``x`` rounded for a report, or None where it is not finite (JSON has no infinities)."""
    return round(float(x), digits) if math.isfinite(x) else None


def percentiles(values, digits: int = 3) -> dict[str, float]:
    """The 5th, 50th and 95th percentiles, as the reports give them."""
    return {p: round(float(np.percentile(values, q)), digits) for p, q in (("p5", 5), ("p50", 50), ("p95", 95))}


def summarize(log) -> dict[str, Any] | None:
    """Per UE type: samples, SINR and throughput percentiles; handover and failure counts.
    None for a run without the radio network."""
    ues = [r for _, r in ue_rows(log)]
    if not ues:
        return None
    events = [m.data for m in log.decoded(NETWORK_EVENTS)]
    kinds: dict[str, Any] = {}
    for kind in sorted({u["UE_type"] for u in ues}):
        mine = [u for u in ues if u["UE_type"] == kind]
        sinr = np.array([u["sinr_db"] for u in mine if u["sinr_db"] is not None])
        thr = np.array([u["throughput_mbps"] for u in mine])
        ids = {u["UE_Id"] for u in mine}
        kinds[kind] = {
            "ues": len(ids), "samples": len(mine),
            "sinr_db": percentiles(sinr) if sinr.size else None,
            "throughput_mbps": percentiles(thr),
            **({"ul_sinr_db": percentiles(ul)}
               if (ul := np.array([u["ul_sinr_db"] for u in mine if u.get("ul_sinr_db") is not None])).size else {}),
            "handovers": sum(1 for e in events if e["event"] == "handover" and e["UE_Id"] in ids),
            "rlf": sum(1 for e in events if e["event"] == "rlf" and e["UE_Id"] in ids),
        }
    summary: dict[str, Any] = {"ue_types": kinds, "events": len(events)}
    transfers = transfer_groups(log)
    if transfers:
        summary["transfers"] = {
            name: {"delivered": len(done), "lost": lost, "bytes_mean": round(float(np.mean([x["bytes"] for x in done])))
                   if done else None,
                   "delay_s": percentiles([x["delay_s"] for x in done], 6) if done else None,
                   "upt_mbps": percentiles([x["upt_mbps"] for x in done]) if done else None}
            for name, (done, lost) in transfers.items()}
    return summary


def transfer_groups(log) -> dict[str, tuple[list[dict], int]]:
    """``network.transfers`` by kind and direction (``ftp downlink``, ``3D.camera.* uplink``: a
    carried topic with its UE as ``*``): (the completed transfers, how many were lost)."""
    groups: dict[str, tuple[list[dict], int]] = {}
    for m in log.decoded(NETWORK_TRANSFERS):
        x = m.data
        source = x["source"]
        head, _, last = source.rpartition(".")
        if last == x["UE_Id"]:
            source = f"{head}.*"
        done, lost = groups.get(f"{source} {x['direction']}", ([], 0))
        groups[f"{source} {x['direction']}"] = (done, lost + 1) if x.get("lost") else ([*done, x], lost)
    return groups


def figures(log, out: pathlib.Path) -> list[pathlib.Path]:
    """Draws the network figures of ``log`` (a :class:`caviar.RunLog`) into ``out``."""
    summary = summarize(log)
    if summary is None:
        return []
    plt = pyplot_into(out)
    ues = [r for _, r in ue_rows(log)]
    kinds = sorted({u["UE_type"] for u in ues})
    uplink = any("ul_sinr_db" in u for u in ues)
    fig, axes = plt.subplots(2 if uplink else 1, 2, figsize=(11, 8 if uplink else 4), squeeze=False)
    for row, (prefix, link) in enumerate((("", "downlink"), ("ul_", "uplink"))[:2 if uplink else 1]):
        _cdf(axes[row, 0], {k: np.array([u[f"{prefix}sinr_db"] for u in ues if u["UE_type"] == k
                                         and u.get(f"{prefix}sinr_db") is not None]) for k in kinds},
             "SINR on the serving cell (dB)")
        _cdf(axes[row, 1], {k: np.array([u[f"{prefix}throughput_mbps"] for u in ues if u["UE_type"] == k
                                         and f"{prefix}throughput_mbps" in u]) for k in kinds}, "throughput (Mbit/s)")
        axes[row, 0].set_title(f"{link} SINR per UE type")
        axes[row, 1].set_title(f"{link} throughput per UE type")
    cdfs = save_figure(fig, out / "network-cdf.png")

    # The map: UE trails, sites and sector boresights, handovers where they happened.
    track: dict[str, dict[int, tuple[float, float]]] = {}
    for m in log.decoded(POSITIONS):
        p = m.data["position"]
        track.setdefault(m.data["UE_Id"], {})[m.step] = (p["x"], p["y"])
    fig, ax = plt.subplots(figsize=(7, 7))
    for pts in track.values():
        xy = np.array([pts[s] for s in sorted(pts)])
        ax.plot(xy[:, 0], xy[:, 1], color="0.75", lw=0.8)
    for s in _sites(log):
        x, y = s["position"][:2]
        ax.plot(x, y, "k^", ms=9)
        ax.annotate(s["name"], (x, y), textcoords="offset points", xytext=(5, 5))
        for az in s.get("azimuths_deg", [0.0, 120.0, 240.0]):
            ax.plot([x, x + 40 * np.cos(np.radians(az))], [y, y + 40 * np.sin(np.radians(az))], "k-", lw=1)
    _beams(ax, log, track)
    step_of = {round(t, 9): s for s, t in zip(log.messages["step"].to_list(), log.messages["time"].to_list(),
                                                strict=True)}
    marks = {"handover": ("o", "tab:blue"), "rlf": ("x", "tab:red"), "coverage_lost": ("s", "tab:orange")}
    for kind, (marker, color) in marks.items():
        where = [track[e["UE_Id"]][step_of[round(e["time"], 9)]] for m in log.decoded(NETWORK_EVENTS)
              if (e := m.data)["event"] == kind and e["UE_Id"] in track
              and step_of.get(round(e["time"], 9)) in track[e["UE_Id"]]]
        if where:
            a = np.array(where)
            ax.scatter(a[:, 0], a[:, 1], marker=marker, color=color, label=f"{kind} ({len(where)})", zorder=3)
    ax.set(xlabel="x (m)", ylabel="y (m)", title="handovers", aspect="equal")
    ax.grid(True)
    if ax.get_legend_handles_labels()[0]:  # (nothing to name in a run without handovers or beams)
        ax.legend(loc="upper right")
    hmap = save_figure(fig, out / "network-handovers.png")
    made = [cdfs, hmap]
    groups = {k: v[0] for k, v in transfer_groups(log).items() if v[0]}
    if groups:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4), squeeze=False)
        _cdf(axes[0, 0], {k: np.array([x["delay_s"] for x in v]) for k, v in groups.items()},
             "delay from queued to delivered (s)")
        _cdf(axes[0, 1], {k: np.array([x["upt_mbps"] for x in v]) for k, v in groups.items()},
             "user-perceived throughput (Mbit/s)")
        axes[0, 0].set(xscale="log", title="file and message delay")
        axes[0, 1].set(xscale="log", title="user-perceived throughput")
        made.append(save_figure(fig, out / "network-transfers.png"))
    return [*made, save_numbers(summary, out / "network.json", indent=2)]


def jain_index(x: np.ndarray) -> float:
    """Jain's fairness index (Σx)² / (n·Σx²): 1 when all are equal, 1/n when one gets all."""
    x = np.asarray(x, dtype=float)
    s2 = float((x ** 2).sum())
    return float(x.sum() ** 2 / (x.size * s2)) if s2 > 0 else math.nan
