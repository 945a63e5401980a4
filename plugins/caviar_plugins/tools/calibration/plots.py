"""The calibration's figures: each metric's CDF over the 3GPP companies' band, the two
channels of the side-by-side, and where the ray-traced UEs lose."""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from caviar_plugins.tools.calibration.config import METRICS, PERCENTILES, cell_radius


def draw(result: dict[str, Any], ref: dict[str, tuple[np.ndarray, np.ndarray]] | None, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.array(PERCENTILES) / 100
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    labels = {"coupling_loss_db": "coupling loss (dB)", "geometry_sinr_db": "geometry SINR (dB)",
              "wideband_sir_db": "wideband SIR (dB)"}
    for ax, metric in zip(axes, METRICS, strict=True):
        if ref is not None:
            pct, curves = ref[metric]
            ax.fill_betweenx(pct / 100, curves.min(axis=0), curves.max(axis=0), color="0.85",
                             label=f"3GPP companies ({len(curves)}): min–max")
            ax.plot(np.median(curves, axis=0), pct / 100, "k--", lw=1, label="companies' median")
        ax.plot(result[metric], p, "C3", lw=2, label=f"CAVIAR ({result['samples']} UEs)")
        ax.set(xlabel=labels[metric], ylabel="CDF", ylim=(0, 1))
        ax.grid(True)
        ax.legend(loc="lower right", fontsize=8)
    fig.suptitle(f"TR 38.901 phase-1 calibration: {result['settings']['scenario']}, "
                 f"{result['settings']['carrier_hz'] / 1e9:g} GHz, {result['drops']} drops")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_side_by_side(result: dict[str, Any], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.array(PERCENTILES) / 100
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    labels = {"coupling_loss_db": "coupling loss (dB)", "geometry_sinr_db": "geometry SINR (dB)",
              "wideband_sir_db": "wideband SIR (dB)"}
    styles = {"ray-traced": ("C3", "-"), "38.901-umi": ("C0", "--")}
    for ax, metric in zip(axes, METRICS, strict=True):
        for channel, r in result["channels"].items():
            colour, ls = styles.get(channel, ("k", ":"))
            lost = f", {r['uncovered']} more with no traced path" if r["uncovered"] else ""
            ax.plot(r[metric], p, color=colour, ls=ls, lw=2, label=f"{channel} ({r['samples']} UEs{lost})")
        ax.set(xlabel=labels[metric], ylabel="CDF", ylim=(0, 1))
        ax.grid(True)
        ax.legend(loc="lower right", fontsize=8)
    s = result["settings"]
    fig.suptitle(f"Ray-traced ({pathlib.Path(s['raytracing']['scene']).parent.parent.name or 'scene'}) against "
                 f"TR 38.901 UMi: 7 sites × 3 sectors, ISD {s['layout']['isd_m']:g} m, "
                 f"{s['carrier_hz'] / 1e9:g} GHz, {result['drops']} drops, outdoor UEs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_where(result: dict[str, Any], ues: dict[str, list[dict[str, Any]]], scene: Any,
               path: pathlib.Path) -> None:
    """Where the channels differ: the ray-traced UEs' coupling loss on the map (buildings
    grey, UEs no traced path reaches as red crosses), and both channels' coupling loss
    against the distance to the serving site beside free space (Friis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from caviar_plugins.constants import SPEED_OF_LIGHT
    from caviar_plugins.network.layout import LayoutSettings, site_positions
    from caviar_plugins.network.raytraced import NO_PATH_DB
    from caviar_plugins.rt.scene import open_sky

    s = result["settings"]
    layout = LayoutSettings(**{**s["layout"], "center_m": tuple(s["layout"]["center_m"])})
    sites = site_positions(layout)
    reach = np.abs(sites - layout.center_m).max() + cell_radius(s["layout"]) + 20.0
    cell = 4.0
    gx = np.arange(layout.center_m[0] - reach, layout.center_m[0] + reach, cell)
    gy = np.arange(layout.center_m[1] - reach, layout.center_m[1] + reach, cell)
    xx, yy = np.meshgrid(gx, gy)
    built = ~open_sky(scene, np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 1.5)], -1)).reshape(xx.shape)

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(15, 6.5))
    ax.imshow(np.where(built, 0.75, 1.0), cmap="gray", vmin=0, vmax=1, origin="lower",
              extent=(gx[0] - cell / 2, gx[-1] + cell / 2, gy[0] - cell / 2, gy[-1] + cell / 2))
    traced = ues["ray-traced"]
    xy = np.array([u["position_m"][:2] for u in traced])
    loss = np.array([u["coupling_loss_db"] if u["coupling_loss_db"] is not None else np.inf for u in traced])
    lost = loss >= -NO_PATH_DB - 50.0
    sc = ax.scatter(xy[~lost, 0], xy[~lost, 1], c=loss[~lost], s=10, cmap="viridis_r",
                    vmin=np.percentile(loss[~lost], 2), vmax=np.percentile(loss[~lost], 98))
    ax.scatter(xy[lost, 0], xy[lost, 1], marker="x", color="red", s=18, label=f"no traced path ({lost.sum()})")
    ax.scatter(sites[:, 0], sites[:, 1], marker="^", color="black", s=60, label="sites (10 m)")
    fig.colorbar(sc, ax=ax, label="ray-traced coupling loss (dB)")
    ax.set(xlabel="x (m, east)", ylabel="y (m, north)", title="Ray-traced: where the UEs lose", aspect="equal")
    ax.legend(loc="upper right", fontsize=8)

    site_of = {f"S{i}": xy_site for i, xy_site in enumerate(sites)}
    for channel, colour in (("38.901-umi", "C0"), ("ray-traced", "C3")):
        rows = [u for u in ues[channel] if u["serving_cell"] is not None
                and u["coupling_loss_db"] < -NO_PATH_DB - 50.0]
        d = np.array([np.hypot(*(np.array(u["position_m"][:2]) - site_of[u["serving_cell"].split("/")[0]]))
                      for u in rows])
        bx.scatter(d, [u["coupling_loss_db"] for u in rows], s=6, alpha=0.5, color=colour, label=channel)
    d = np.linspace(10, float(reach), 200)
    lam = SPEED_OF_LIGHT / s["carrier_hz"]
    friis = 20 * np.log10(4 * np.pi * np.hypot(d, s["layout"]["height_m"] - 1.5) / lam)
    bx.plot(d, friis, "k-", lw=1, label="free space (Friis), 0 dBi")
    bx.plot(d, friis - 18.0, "k:", lw=1, label="free space, the panel's 18 dBi peak")
    bx.set(xscale="log", xlabel="2D distance to the serving site (m)", ylabel="coupling loss (dB)",
           title="Coupling loss against distance")
    bx.grid(True, which="both", alpha=0.4)
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
