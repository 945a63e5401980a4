"""The figures of a material fit (``fit-scene``'s fit.png) and of a self-calibrating run
(``caviar-core report`` of a run with a ``scene-fitter`` module)."""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.report_figures import pyplot_into, save_figure


def plot_fit(result: Any, data: Any, path: pathlib.Path) -> pathlib.Path:
    """Left: the fit and held-out RMSE at every evaluation (coarse search, then descent).
    Right: measured against predicted received power of the held-out samples, before and
    after."""
    plt = pyplot_into(path.parent)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    hist = result.history
    x = np.arange(len(hist))
    a.plot(x, [r["fit_rmse_db"] for r in hist], label="fit samples")
    a.plot(x, [r["held_out_rmse_db"] for r in hist], label="held-out samples")
    n_search = sum(r["phase"] == "search" for r in hist)
    if n_search:
        a.axvline(n_search - 0.5, color="grey", lw=0.8, ls="--")
        a.text(n_search - 0.5, a.get_ylim()[1], " descent", va="top", fontsize=8, color="grey")
    a.set_xlabel("evaluation (coarse search, then gradient steps)")
    a.set_ylabel("RMSE of received power (dB)")
    a.set_title("Material fit")
    a.legend()
    held = result.holdout_mask if result.holdout_mask is not None and result.holdout_mask.any() else \
        np.ones(len(data), dtype=bool)
    measured = data.power_dbm[held]
    for key, marker in (("before", "x"), ("after", "o")):
        pred = result.predicted_dbm[key][held]
        ok = np.isfinite(pred)
        rm = result.rmse_db["held_out" if result.holdout_mask is not None and result.holdout_mask.any() else "fit"][key]
        b.scatter(measured[ok], pred[ok], s=12, marker=marker, alpha=0.7, label=f"{key} ({rm:.2f} dB RMSE)")
    lo, hi = float(np.min(measured)), float(np.max(measured))
    b.plot([lo, hi], [lo, hi], color="black", lw=0.8)
    b.set_xlabel("measured (dBm)")
    b.set_ylabel("predicted by the twin (dBm)")
    b.set_title("Held-out samples")
    b.legend()
    return save_figure(fig, path)
