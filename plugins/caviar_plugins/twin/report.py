"""Figures of a self-calibrating run, for ``caviar-core report`` (entry-point group
``caviar.report``): the twin's prediction error of each new measurement over the run (the
refits marked) and the learned material values, with ``twin.json`` holding the numbers.

    caviar-core report runs/self-calibrating-001 --out report/
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.report_figures import pyplot_into, save_figure, save_numbers
from caviar_plugins.schema import TWIN_FIT


def summarize(log) -> dict[str, Any] | None:
    """The prediction error before the first refit and after the last, per refit what was
    learned; None for a run without a ``scene-fitter``."""
    fits = log.decoded(TWIN_FIT)
    if not fits:
        return None
    errors = [(m.time, m.data["prediction_error_db"]) for m in fits
              if "prediction_error_db" in m.data and m.data["prediction_error_db"] is not None]
    refits = [m.data for m in fits if "refit" in m.data]
    first = refits[0]["time"] if refits else float("inf")
    last = refits[-1]["time"] if refits else float("inf")

    def rms(rows):
        return round(float(np.sqrt(np.mean(np.square([e for _, e in rows])))), 3) if rows else None

    return {"prediction_error_db": {"before_first_refit": rms([r for r in errors if r[0] <= first]),
                                    "after_last_refit": rms([r for r in errors if r[0] > last])},
            "refits": [{"time": r["time"], "samples": r["samples"], "learned": r["learned"], "rmse_db": r["rmse_db"],
                        "not_identifiable": r["not_identifiable"], "confounded": r.get("confounded", {}),
                        "ambiguous": r.get("ambiguous", {}),
                        **({"delay_spread_ns": r["delay_spread_ns"]} if "delay_spread_ns" in r else {})}
                       for r in refits]}


def hidden_truth(log) -> dict[str, float]:
    """``{"material.property": value}`` of the hidden truth of a run's ``measurement-emulator``
    (its ``truth`` parameter, from the run's config), empty without one: what the learned values
    are drawn against."""
    import tomllib

    try:
        modules = tomllib.loads(log.config_text).get("modules", {})
    except (OSError, ValueError, AttributeError):
        return {}
    out: dict[str, float] = {}
    for table in modules.values():
        if isinstance(table, dict) and table.get("plugin") == "measurement-emulator":
            for material, props in (table.get("params", {}).get("truth") or {}).items():
                for prop, value in (props.items() if isinstance(props, dict) else ()):
                    if isinstance(value, (int, float)):
                        out[f"{material}.{prop}"] = float(value)
    return out


def figures(log, out: pathlib.Path) -> list[pathlib.Path]:
    """Draws the twin's figure of ``log`` (a :class:`caviar.RunLog`) into ``out``."""
    summary = summarize(log)
    if summary is None:
        return []
    plt = pyplot_into(out)
    fits = log.decoded(TWIN_FIT)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.4))
    rows = [(m.time, m.data["prediction_error_db"]) for m in fits if m.data.get("prediction_error_db") is not None]
    if rows:
        t, e = np.array(rows).T
        ax.plot(t, np.abs(e), ".", ms=4, alpha=0.6, label="|error| of each new measurement")
        k = min(10, len(e))
        trailing = [np.sqrt(np.mean(e[max(0, i - k + 1):i + 1] ** 2)) for i in range(len(e))]
        ax.plot(t, trailing, label=f"RMS of the last {k}")
    for r in summary["refits"]:
        ax.axvline(r["time"], color="grey", lw=0.8, ls="--")
    ax.set(xlabel="time (s)", ylabel="prediction error (dB)",
           title="The twin's prediction of each new measurement (dashed: refits)")
    ax.legend()
    names = sorted({k for r in summary["refits"] for k in r["learned"]})
    truth = hidden_truth(log)
    for name in names:
        pts = [(r["time"], r["learned"][name]) for r in summary["refits"] if name in r["learned"]]
        line, = bx.plot(*np.array(pts).T, "o-", label=name)
        if name in truth:
            bx.axhline(truth[name], color=line.get_color(), ls=":", lw=1.2, label=f"{name}: hidden truth")
    bx.set(xlabel="time (s)", ylabel="learned value", title="Learned materials per refit")
    if names:
        bx.legend(fontsize=8)
    return [save_figure(fig, out / "twin.png"), save_numbers(summary, out / "twin.json")]
