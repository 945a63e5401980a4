"""Figures of a run with ``ns3-network``, for ``caviar-core report`` (entry-point group
``caviar.report``): per UE, each image's end-to-end delay and lost share over the flight
beside the link (the loss set from the channel, and the SINR the eNB measured), the PSNR
the detector saw, and ``ns3.json`` with the numbers.

    caviar-core report runs/sar-ns3-001 --out report/
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.network.report import percentiles
from caviar_plugins.report_figures import pyplot_into, save_figure, save_numbers
from caviar_plugins.schema import IMAGE_QUALITY, NS3_LINK


def summarize(log) -> dict[str, Any] | None:
    """Per UE: images sent and complete, delay percentiles, loss, PSNR; None for a run
    without ``ns3-network``."""
    links = log.decoded(NS3_LINK)
    if not links:
        return None
    images = [m.data for m in log.decoded(IMAGE_QUALITY) if "bytes_sent" in m.data]
    ues: dict[str, Any] = {}
    for ue in sorted({m.data["UE_Id"] for m in links}):
        mine = [d for d in images if d["UE_Id"] == ue]
        delays = np.array([d["delay_s"] for d in mine if d["delay_s"] is not None])
        sent = sum(d["bytes_sent"] for d in mine)
        ues[ue] = {
            "images": len(mine), "complete": sum(d["complete"] for d in mine),
            "bytes_sent": sent, "bytes_received": sum(d["bytes_received"] for d in mine),
            "packets_sent": sum(d["packets_sent"] for d in mine),
            "packets_lost": sum(d["packets_lost"] for d in mine),
            "loss_rate": round(1 - sum(d["bytes_received"] for d in mine) / sent, 4) if sent else None,
            "delay_s": percentiles(delays, 5) if len(delays) else None,
            "psnr_db_median": round(float(np.median([d["psnr_db"] for d in mine])), 2) if mine else None,
        }
    return {"ran": links[0].data["ran"], "ues": ues}


def figures(log, out: pathlib.Path) -> list[pathlib.Path]:
    """Draws the ns-3 figures of ``log`` (a :class:`caviar.RunLog`) into ``out``."""
    summary = summarize(log)
    if summary is None:
        return []
    plt = pyplot_into(out)
    links = log.decoded(NS3_LINK)
    images = [m for m in log.decoded(IMAGE_QUALITY) if "bytes_sent" in m.data]
    fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    ax, bx, cx = axes
    for k, ue in enumerate(summary["ues"]):
        colour = f"C{k}"
        mine = [m.data for m in images if m.data["UE_Id"] == ue]
        sent = np.array([d["sent_at"] for d in mine])
        delay = np.array([np.nan if d["delay_s"] is None else 1e3 * d["delay_s"] for d in mine])
        ax.plot(sent, delay, ".", color=colour, ms=4, label=f"{ue}: delay of complete images")
        late = [d["sent_at"] for d in mine if not d["complete"]]
        if late:
            ax.plot(late, np.full(len(late), np.nanmax(delay) if np.isfinite(delay).any() else 1.0), "x",
                    color="tab:red", ms=4, label=f"{ue}: incomplete at the deadline")
        bx.plot(sent, [100 * d["loss_rate"] for d in mine], color=colour, lw=1, label=f"{ue}: bytes lost (%)")
        bx2 = bx.twinx()
        bx2.plot(sent, [d["psnr_db"] for d in mine], color=colour, ls=":", lw=1)
        bx2.set_ylabel("PSNR at the detector (dB, dotted)")
        ml = [m.data for m in links if m.data["UE_Id"] == ue]
        t = [d["time"] for d in ml]
        cx.plot(t, [np.nan if d["loss_db"] is None else -d["loss_db"] for d in ml], color=colour,
                label=f"{ue}: channel gain set in ns-3 (dB)")
        if any(d["sinr_db"] is not None for d in ml):
            cx2 = cx.twinx()
            cx2.plot(t, [np.nan if d["sinr_db"] is None else d["sinr_db"] for d in ml], color="tab:orange", lw=1)
            cx2.set_ylabel("uplink SINR at the eNB (dB, orange)")
    ax.set(ylabel="end-to-end delay (ms)", title=f"Images over ns-3 ({summary['ran']})")
    bx.set(ylabel="image bytes lost (%)", ylim=(-2, 102))
    cx.set(xlabel="time (s)", ylabel="gain (dB)")
    for axis in axes:
        axis.grid(True)
        axis.legend(fontsize=8, loc="upper left")
    return [save_figure(fig, out / "ns3.png"), save_numbers(summary, out / "ns3.json")]
