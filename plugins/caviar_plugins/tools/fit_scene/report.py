"""The figures of a material fit (``fit-scene``'s fit.png) and of a self-calibrating run
(``caviar-core report`` of a run with a ``scene-fitter`` module)."""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.report_figures import pyplot_into, save_figure


def plot_fit(result: Any, data: Any, path: pathlib.Path) -> pathlib.Path:
    """Left: the fit and held-out RMSE at every evaluation (searches, descents and restarts in
    the order they ran; the descents' steps marked).
    Middle: measured against predicted received power of the held-out samples, before and
    after. Right, with power-delay profiles among the measurements: the same for their RMS
    delay spread (never fitted)."""
    plt = pyplot_into(path.parent)
    spreads = result.delay_spread_s
    fig, axes = plt.subplots(1, 3 if spreads else 2, figsize=(16.5 if spreads else 11, 4.2))
    a, b = axes[0], axes[1]
    hist = result.history
    x = np.arange(len(hist))
    fit_err = np.array([r["fit_rmse_db"] for r in hist], dtype=float)
    a.plot(x, fit_err, lw=0.6, label="fit samples")
    a.plot(x, [r["held_out_rmse_db"] for r in hist], lw=0.6, alpha=0.6, label="held-out samples")
    descent = np.array([r["phase"] == "descent" for r in hist], dtype=bool)
    if descent.any():
        a.scatter(x[descent], fit_err[descent], s=8, color="black", zorder=3, label="descent steps (fit)")
    a.set_yscale("log")
    a.set_xlabel("evaluation (search sweeps, descents, restarts, in order)")
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
    if spreads:
        _plot_spreads(axes[2], spreads, held, result.delay_spread_ns,
                      "held_out" if result.holdout_mask is not None and result.holdout_mask.any() else "fit")
    return save_figure(fig, path)


def _plot_spreads(c: Any, spreads: dict[str, np.ndarray], held: np.ndarray, errors: dict[str, Any],
                  which: str) -> None:
    """Measured against predicted RMS delay spread (ns) of the samples ``held`` with a profile
    (``which``: the held-out ones, or all fitted ones where none was held out)."""
    measured = spreads["measured"][held] * 1e9
    for key, marker in (("before", "x"), ("after", "o")):
        pred = spreads[key][held] * 1e9
        ok = np.isfinite(pred) & np.isfinite(measured)
        err = errors[which][key]
        c.scatter(measured[ok], pred[ok], s=12, marker=marker, alpha=0.7,
                  label=f"{key} ({'-' if err is None else f'{err:.1f}'} ns RMS error)")
    ok = np.isfinite(measured)
    if ok.any():
        lo, hi = float(np.min(measured[ok])), float(np.max(measured[ok]))
        c.plot([lo, hi], [lo, hi], color="black", lw=0.8)
    c.set_xlabel("measured RMS delay spread (ns)")
    c.set_ylabel("predicted by the twin (ns)")
    c.set_title(f"{'Held-out' if which == 'held_out' else 'Fitted'} samples' delay spread (not fitted on)")
    c.legend()
