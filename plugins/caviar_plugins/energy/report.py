"""Figures of a run with UAV energy, for ``caviar-core report`` (entry-point group
``caviar.report``): per UAV its state of charge and power over the flight (the return
home and the rescues marked), its track coloured by state of charge, and ``energy.json``
with the numbers.

    caviar-core report runs/uav-energy-001 --out report/
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.report_figures import pyplot_into, save_figure, save_numbers
from caviar_plugins.schema import ENERGY, POSITIONS, RESCUE, RESULT, RETURN_HOME


def summarize(log) -> dict[str, Any] | None:
    """Per UAV: energy used, final state of charge, mean power, when it was sent home;
    the mission's energy per rescue. None for a run without ``uav.energy``."""
    energy = log.decoded(ENERGY)
    if not energy:
        return None
    sent = {m.data["UE_Id"]: m.time for m in log.decoded(RETURN_HOME)}
    uavs: dict[str, Any] = {}
    for ue in sorted({m.data["UE_Id"] for m in energy}):
        mine = [m for m in energy if m.data["UE_Id"] == ue]
        last = mine[-1].data
        seconds = mine[-1].time - mine[0].time
        uavs[ue] = {"energy_wh": last["energy_wh"], "soc": last["soc"],
                    "mean_power_w": round(last["energy_wh"] * 3600 / seconds, 2) if seconds > 0 else None,
                    "flight_s": round(seconds, 3), "sent_home_at_s": sent.get(ue)}
    result = log.decoded(RESULT)
    summary: dict[str, Any] = {"uavs": uavs}
    if result:
        summary["rescued"] = result[-1].data["rescued"]
        summary["energy_per_rescue_wh"] = result[-1].data.get("energy_per_rescue_wh")
    return summary


def _over_time(ax, bx, summary: dict[str, Any], energy, rescues, sent: dict[str, float]) -> None:
    """State of charge and power per UAV, the reserve, the return and the rescues marked."""
    for k, ue in enumerate(summary["uavs"]):
        mine = [m for m in energy if m.data["UE_Id"] == ue]
        t = np.array([m.time for m in mine])
        colour = f"C{k}"
        ax.plot(t, [100 * m.data["soc"] for m in mine], color=colour, label=ue)
        ax.axhline(100 * mine[-1].data["reserve_wh"] / mine[-1].data["capacity_wh"], color=colour, ls=":", lw=1)
        bx.plot(t, [m.data["power_w"] for m in mine], color=colour, lw=1, label=ue)
        for axis in (ax, bx):
            if ue in sent:
                axis.axvline(sent[ue], color=colour, ls="--", lw=1)
            for r in rescues:
                if r.data["UE_Id"] == ue:
                    axis.axvline(r.time, color="tab:green", lw=0.8, alpha=0.7)
    ax.set(xlabel="time (s)", ylabel="state of charge (%)",
           title="Battery (dotted: reserve; dashed: sent home; green: rescues)", ylim=(0, 100))
    bx.set(xlabel="time (s)", ylabel="power (W)", title="Power: propulsion, radio and computing")
    for axis in (ax, bx):
        axis.grid(True)
        axis.legend(fontsize=8)


def _track(fig, cx, log, summary: dict[str, Any], energy, rescues) -> None:
    """Each UAV's track coloured by its state of charge, its home and the rescues."""
    track: dict[str, dict[int, tuple[float, float]]] = {}
    for m in log.decoded(POSITIONS):
        track.setdefault(m.data["UE_Id"], {})[m.step] = (m.data["position"]["x"], m.data["position"]["y"])
    sc = None
    for ue in summary["uavs"]:
        mine = [m for m in energy if m.data["UE_Id"] == ue]
        cx.plot(*mine[0].data["home"][:2], "k^", ms=9)
        points = [(track.get(ue, {}).get(m.step), m.data["soc"]) for m in mine]
        xy = np.array([q for q, _ in points if q is not None])
        soc = np.array([s for q, s in points if q is not None])
        if len(xy):
            sc = cx.scatter(xy[:, 0], xy[:, 1], c=100 * soc, s=6, cmap="RdYlGn", vmin=0, vmax=100)
    for r in rescues:
        cx.plot(r.data["x"], r.data["y"], "b*", ms=10)
    if sc is not None:
        fig.colorbar(sc, ax=cx, label="state of charge (%)")
    cx.set(xlabel="x (m)", ylabel="y (m)", title="Track (▲ home, ★ rescues)", aspect="equal")


def figures(log, out: pathlib.Path) -> list[pathlib.Path]:
    """Draws the energy figures of ``log`` (a :class:`caviar.RunLog`) into ``out``."""
    summary = summarize(log)
    if summary is None:
        return []
    plt = pyplot_into(out)
    energy = log.decoded(ENERGY)
    rescues = log.decoded(RESCUE)
    sent = {m.data["UE_Id"]: m.time for m in log.decoded(RETURN_HOME)}
    fig, (ax, bx, cx) = plt.subplots(1, 3, figsize=(17, 4.8))
    _over_time(ax, bx, summary, energy, rescues, sent)
    _track(fig, cx, log, summary, energy, rescues)
    return [save_figure(fig, out / "energy.png"), save_numbers(summary, out / "energy.json")]
