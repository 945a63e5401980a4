"""``caviar-core calibrate 38.901``: the phase-1 (large-scale) calibration of TR 38.901 §7.8.1
(R1-165974; Table 7.8-1 settings, no fast fading), run through the ``radio-network``
plugin's own cells, measurements and SINR, as every blueprint runs.

    caviar-core calibrate 38.901 --scenario UMa --carrier 6e9 --drops 20

Each engine step is one drop: the network drops 10 UEs in each of the 57 sectors of the
19-site wrapped-around hexagonal layout, every UE attaches to its strongest cell (no
handover margin) and reports, on ``network.ue``, its coupling loss, its geometry SINR
(with noise) and its wideband SIR (without). The command writes
``<out>/<scenario>-<carrier>GHz.json`` (the three CDFs at the percentiles 0..100, the drops
and the settings; coupling loss as a positive loss) and a ``.png`` that draws each CDF
over the band of the 3GPP companies' curves where the shipped file has them
(``--reference``, :data:`COMPANIES` by default).

    caviar-core calibrate ray-traced --scene blueprints/osm-city/scene/scene.xml --drops 20

sets the ray-traced channel beside the stochastic one: the UMi-like layout of 7 sites at
ISD 200 m placed in a city scene (``--center``, or the centre nearest the scene's middle
with every site in the open), run once with ``channel = "ray-traced"`` and once with
``38.901-umi``, outdoor UEs only; it writes both channels' CDFs, their difference at the
percentiles 5, 50 and 95, and a map of where the ray-traced UEs lose
(``<out>/raytraced-vs-38.901-umi{.json,.png,-map.png}``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time
from typing import Any

import numpy as np

from caviar_plugins.assets import DATA

# TR 38.901 Table 7.8-1 (large-scale calibration): per scenario the layout, and per
# carrier the BS power and the bandwidth (with the NR numerology used here).
LAYOUTS = {"uma": {"isd_m": 500.0, "height_m": 25.0, "min_distance_m": 35.0},
           "umi": {"isd_m": 200.0, "height_m": 10.0, "min_distance_m": 10.0}}
POWER_DBM = {("uma", 6e9): 49.0, ("umi", 6e9): 44.0, ("uma", 30e9): 35.0, ("umi", 30e9): 35.0,
             ("uma", 70e9): 35.0, ("umi", 70e9): 35.0}
BANDWIDTH = {6e9: (20e6, 30e3), 30e9: (100e6, 120e3), 70e9: (100e6, 120e3)}
NOISE_FIGURE_DB = 9.0
ELECTRICAL_TILT_DEG = 12.0  # a zenith of 102° (UMa and UMi)
UES_PER_SECTOR = 10
METRICS = ("coupling_loss_db", "geometry_sinr_db", "wideband_sir_db")
# The companies' file names these metrics so (coupling loss as a gain there).
REFERENCE_NAMES = {"coupling_loss_db": "coupling_loss", "geometry_sinr_db": "geometry_sinr",
                   "wideband_sir_db": "wideband_sir"}
PERCENTILES = list(range(101))
COMPANIES = DATA / "3gpp-phase1-uma-6ghz.json"
"""The 20 companies' phase-1 CDFs of UMa at 6 GHz (R1-165974; ``Phase1Calibration_v42_CMCC.xlsx``
as NVIDIA Aerial encodes it), shipped with the package: the band the calibration is drawn over."""


class CalibrationError(ValueError):
    """A scenario or carrier Table 7.8-1 does not define."""


def settings(scenario: str, carrier_hz: float) -> dict[str, Any]:
    """Table 7.8-1's settings of ``scenario`` (``UMa``, ``UMi``) at ``carrier_hz``."""
    key = scenario.lower()
    if key == "rma":
        raise CalibrationError("--scenario: TR 38.901 Table 7.8-1 defines the large-scale calibration for "
                               "UMa, UMi and indoor office only; RMa has no calibration row (its channel, "
                               "channel = \"38.901-rma\", runs in any network)")
    if key not in LAYOUTS:
        raise CalibrationError(f"--scenario: expected UMa or UMi (TR 38.901 Table 7.8-1), got {scenario!r}")
    if (key, carrier_hz) not in POWER_DBM:
        raise CalibrationError(f"--carrier: Table 7.8-1 calibrates at 6e9, 30e9 and 70e9 Hz, got {carrier_hz:g}")
    bandwidth, scs = BANDWIDTH[carrier_hz]
    return {"scenario": scenario, "carrier_hz": carrier_hz, "tx_power_dbm": POWER_DBM[(key, carrier_hz)],
            "bandwidth_hz": bandwidth, "subcarrier_spacing_hz": scs, "noise_figure_db": NOISE_FIGURE_DB,
            "layout": {"kind": "hex", "rings": 2, "sectors": 3, "wraparound": True, "indoor_share": 0.8,
                       "ues_per_sector": UES_PER_SECTOR, "redrop": "every-step", **LAYOUTS[key]},
            "column": {"elements": 10, "spacing_wavelengths": 0.5, "electrical_tilt_deg": ELECTRICAL_TILT_DEG},
            "o2i_high_loss_share": 0.5, "ue_antenna": "omni, 0 dBi", "fast_fading": False,
            "handover_margin_db": 0.0}


def config_toml(s: dict[str, Any], drops: int, seed: int) -> str:
    """The run's configuration: one radio-network module, one drop per step."""
    layout = ", ".join(f"{k} = {json.dumps(v)}" for k, v in s["layout"].items())
    column = ", ".join(f"{k} = {json.dumps(v)}" for k, v in s["column"].items())
    channel = "38.901-" + s["scenario"].lower()
    return f"""# TR 38.901 phase-1 calibration ({s['scenario']}, {s['carrier_hz'] / 1e9:g} GHz), written by
# caviar-core calibrate: one drop per step.
[episode]
ts = 0.001
seed = {seed}
steps = {drops}
stages = ["communications"]

[output]
name = "calibration-{s['scenario'].lower()}"
analysis = ["communications.throughput", "network.ue", "network.events", "network.cells",
            "network.radio_map", "view.radio_map"]

[modules.net]
stage = "communications"
plugin = "radio-network"
subscribe = []
[modules.net.params]
channel = "{channel}"
carrier_hz = {s['carrier_hz']:.1f}
bandwidth_hz = {s['bandwidth_hz']:.1f}
subcarrier_spacing_hz = {s['subcarrier_spacing_hz']:.1f}
tx_power_dbm = {s['tx_power_dbm']}
noise_figure_db = {s['noise_figure_db']}
array = [1, 1]
link_model = "shannon"
report_cells = 1
layout = {{ {layout} }}
column = {{ {column} }}
tr38901 = {{ o2i_high_loss_share = {s['o2i_high_loss_share']} }}
handover = {{ offset_db = 0.0, hysteresis_db = 0.0, l3_filter_k = 0.0, min_rsrp_dbm = -1000.0 }}
"""


def metrics_of(log) -> dict[str, np.ndarray]:
    """The three metrics of every dropped UE the run reported."""
    from caviar_plugins.schema import NETWORK_UE

    rows = [m.data for m in log.decoded(NETWORK_UE) if m.data.get("UE_type") == "dropped"]
    return {"coupling_loss_db": np.array([r["coupling_loss_db"] for r in rows], dtype=float),
            "geometry_sinr_db": np.array([r["sinr_db"] for r in rows], dtype=float),
            "wideband_sir_db": np.array([r["sir_db"] for r in rows], dtype=float)}


def reference(path: pathlib.Path | None, scenario: str,
              carrier_hz: float) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """The companies' CDFs of the scenario per metric: (percentiles [n], values [company, n]),
    coupling loss as a positive loss; None where the file has none."""
    if path is None or not path.exists():
        return None
    data = json.loads(path.read_text())
    entry = data.get("scenarios", {}).get(f"{scenario}-{carrier_hz / 1e9:g}GHz")
    if entry is None:
        return None
    out = {}
    for metric, name in REFERENCE_NAMES.items():
        table = entry["metrics"][name]
        pct = np.array(table["cdf_percentiles"], dtype=float)
        curves = np.array([c for c in table["data"].values()
                           if len(c) == len(pct) and all(v is not None for v in c)], dtype=float)
        if metric == "coupling_loss_db":  # a gain's percentile p is the loss's 100 − p
            curves, pct = -curves[:, ::-1], 100.0 - pct[::-1]
        out[metric] = (pct, curves)
    return out


def compare(ours: dict[str, list[float]], ref: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """At the percentiles 5, 50, 95: ours, the companies' min, median and max, whether ours
    is within their range, and (at 50) its distance to their median."""
    out: dict[str, Any] = {}
    for metric, (pct, curves) in ref.items():
        out[metric] = {}
        for p in (5, 50, 95):
            at = curves[:, int(np.flatnonzero(pct == p)[0])]
            lo, med, hi = float(at.min()), float(np.median(at)), float(at.max())
            v = ours[metric][p]
            out[metric][f"p{p}"] = {"ours": round(v, 2), "min": round(lo, 2), "median": round(med, 2),
                                    "max": round(hi, 2), "within_range": lo <= v <= hi,
                                    "from_median_db": round(v - med, 2)}
    return out


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


def calibrate(scenario: str, carrier_hz: float, drops: int, out: pathlib.Path, seed: int = 1,
              reference_file: pathlib.Path | None = None, progress: bool = True) -> dict[str, Any]:
    """Runs the calibration and writes ``out/<scenario>-<GHz>GHz.{json,png}``; returns
    what the JSON holds."""
    import caviar

    s = settings(scenario, carrier_hz)
    if drops < 1:
        raise CalibrationError(f"--drops: expected at least one drop, got {drops}")
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="caviar-calibration-") as tmp:
        cfg = pathlib.Path(tmp) / "config.toml"
        cfg.write_text(config_toml(s, drops, seed))
        with caviar.Simulation.from_toml(cfg, out=pathlib.Path(tmp) / "runs") as sim:
            log = sim.run(progress=progress)
        values = metrics_of(log)
    wall = time.perf_counter() - started
    result: dict[str, Any] = {"percentiles": PERCENTILES}
    for metric, v in values.items():
        result[metric] = [round(float(x), 3) for x in np.percentile(v, PERCENTILES)]
    result.update(drops=drops, samples=int(values["coupling_loss_db"].size), seed=seed, settings=s,
                  wall_s=round(wall, 1))
    ref = reference(reference_file, s["scenario"], carrier_hz)
    if ref is not None:
        result["reference"] = {"file": reference_file.name if reference_file else None,
                               "companies": int(len(ref["coupling_loss_db"][1])), **compare(result, ref)}
    stem = f"{s['scenario']}-{carrier_hz / 1e9:g}GHz"
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1) + "\n")
    draw(result, ref, out / f"{stem}.png")
    return result


# --- ray-traced against stochastic on one layout -------------------------------------------

SIDE_BY_SIDE_LAYOUT = {"kind": "hex", "rings": 1, "isd_m": 200.0, "height_m": 10.0, "min_distance_m": 10.0,
                       "wraparound": False, "indoor_share": 0.0, "ues_per_sector": UES_PER_SECTOR,
                       "redrop": "every-step"}
"""The UMi-like layout both channels run on: 7 sites × 3 sectors at ISD 200 m, 10 m high,
outdoor UEs (the ray tracer has no building entry loss), no wraparound (a scene does not
repeat)."""
SIDE_BY_SIDE_CHANNELS = ("ray-traced", "38.901-umi")


def _cell_radius(layout: dict[str, Any]) -> float:
    return float(layout["isd_m"]) / np.sqrt(3)


def find_center(scene: Any, layout: dict[str, Any], step_m: float = 10.0) -> tuple[float, float]:
    """A centre for the layout in ``scene`` (Sionna RT) where every site has open sky above
    it (none inside a building) and every sector lies inside the scene's extent; the one
    nearest the scene's middle."""
    from caviar_plugins.network.layout import LayoutSettings, site_positions
    from caviar_plugins.rt.scene import open_sky

    box = scene.mi_scene.bbox()
    lo, hi = np.array(box.min, dtype=float)[:2], np.array(box.max, dtype=float)[:2]
    sites = site_positions(LayoutSettings(**{**layout, "center_m": (0.0, 0.0)}))
    reach = np.abs(sites).max(axis=0) + _cell_radius(layout)
    first, last = lo + reach, hi - reach
    if np.any(first > last):
        raise CalibrationError(f"--scene: the layout ({2 * reach[0]:.0f} × {2 * reach[1]:.0f} m) does not fit in "
                               f"the scene ({hi[0] - lo[0]:.0f} × {hi[1] - lo[1]:.0f} m)")
    middle = np.round((lo + hi) / 2 / step_m) * step_m
    gx, gy = (m + step_m * np.arange(np.ceil((a - m) / step_m), np.floor((b - m) / step_m) + 1)
              for m, a, b in zip(middle, first, last, strict=True))
    centres = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    centres = centres[np.argsort(np.linalg.norm(centres - middle, axis=1), kind="stable")]
    points = np.concatenate([centres[:, None, :] + sites[None], np.full((len(centres), len(sites), 1),
                                                                     float(layout["height_m"]))], axis=-1)
    ok = open_sky(scene, points.reshape(-1, 3)).reshape(len(centres), len(sites)).all(axis=1)
    if not ok.any():
        raise CalibrationError("--center: no centre puts every site of the layout in the open in this scene; "
                               "give one with --center X,Y")
    x, y = centres[int(np.argmax(ok))]
    return float(x), float(y)


def side_by_side_toml(s: dict[str, Any], channel: str, drops: int, seed: int, scene_file: pathlib.Path) -> str:
    """The calibration's configuration with ``channel`` on the side-by-side layout."""
    text = config_toml(s, drops, seed)
    text = text.replace(f'channel = "38.901-{s["scenario"].lower()}"', f'channel = "{channel}"')
    if channel == "ray-traced":
        rt = s["raytracing"]
        text += (f'raytracing = {{ scene = {json.dumps(str(scene_file))}, max_depth = {rt["max_depth"]}, '
                 f'samples_per_src = {rt["samples_per_src"]}, diffraction = true, evolve = "hold", '
                 f'threads = {rt["threads"]} }}\n')
    return text


def _covered(values: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
    """The metrics of the UEs some cell reaches, and how many no cell reaches (no traced
    path: a coupling loss at :data:`~caviar_plugins.network.raytraced.NO_PATH_DB`)."""
    from caviar_plugins.network.raytraced import NO_PATH_DB

    loss = values["coupling_loss_db"]
    ok = np.isfinite(loss) & (loss < -NO_PATH_DB - 50.0)
    return {k: v[ok] for k, v in values.items()}, int((~ok).sum())


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


def side_by_side(scene: str, drops: int, out: pathlib.Path, center: tuple[float, float] | None = None,
                 seed: int = 1, samples_per_src: int = 100_000, max_depth: int = 2, threads: int = 0,
                 progress: bool = True) -> dict[str, Any]:
    """Runs the UMi-like 7-site layout with ``channel = "ray-traced"`` in ``scene`` and with
    ``38.901-umi``, the same drops' settings, and writes
    ``out/raytraced-vs-38.901-umi.{json,png}``: both channels' CDFs and, at the
    percentiles 5, 50 and 95, by how much the ray-traced one differs."""
    import caviar
    from caviar_plugins.rt.scene import load_scene

    if drops < 1:
        raise CalibrationError(f"--drops: expected at least one drop, got {drops}")
    scene_file = pathlib.Path(scene).resolve()
    if not scene_file.is_file():
        raise CalibrationError(f"--scene: expected a Mitsuba scene file (scene build's scene.xml), got {scene!r}")
    s = settings("UMi", 6e9)
    s["layout"] = dict(SIDE_BY_SIDE_LAYOUT)
    if center is None:
        center = find_center(load_scene(str(scene_file)), s["layout"])
    s["layout"]["center_m"] = [round(center[0], 3), round(center[1], 3)]
    s["raytracing"] = {"scene": str(scene), "max_depth": max_depth, "samples_per_src": samples_per_src,
                       "diffraction": True, "threads": threads}
    out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"percentiles": PERCENTILES, "drops": drops, "seed": seed, "channels": {}}
    ues: dict[str, list[dict[str, Any]]] = {}
    for channel in SIDE_BY_SIDE_CHANNELS:
        started = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="caviar-side-by-side-") as tmp:
            cfg = pathlib.Path(tmp) / "config.toml"
            cfg.write_text(side_by_side_toml(s, channel, drops, seed, scene_file))
            with caviar.Simulation.from_toml(cfg, out=pathlib.Path(tmp) / "runs") as sim:
                log = sim.run(progress=progress)
            values, uncovered = _covered(metrics_of(log))
            ues[channel] = dropped_ues(log)
        if values["coupling_loss_db"].size == 0:
            raise CalibrationError(f"--center/--max-depth: no cell reaches any UE with channel {channel!r} "
                                   f"({uncovered} UEs dropped); place the layout elsewhere or trace deeper")
        r: dict[str, Any] = {m: [round(float(x), 3) for x in np.percentile(v, PERCENTILES)] for m, v in values.items()}
        r.update(samples=int(values["coupling_loss_db"].size), uncovered=uncovered,
                 wall_s=round(time.perf_counter() - started, 1))
        result["channels"][channel] = r
    traced, stochastic = (result["channels"][c] for c in SIDE_BY_SIDE_CHANNELS)
    result["difference_db"] = {m: {f"p{q}": round(traced[m][q] - stochastic[m][q], 2) for q in (5, 50, 95)}
                               for m in METRICS}
    s["tr38901"] = "Sionna's UMi: pathloss, LOS probability, shadow fading (no O2I: outdoor UEs), no fast fading"
    result["settings"] = s
    (out / "raytraced-vs-38.901-umi.json").write_text(json.dumps(result, indent=1) + "\n")
    draw_side_by_side(result, out / "raytraced-vs-38.901-umi.png")
    draw_where(result, ues, load_scene(str(scene_file)), out / "raytraced-vs-38.901-umi-map.png")
    return result


def dropped_ues(log) -> list[dict[str, Any]]:
    """Every dropped UE the run reported: its position, serving cell and coupling loss."""
    from caviar_plugins.schema import NETWORK_UE

    return [{"position_m": m.data["position_m"], "serving_cell": m.data["serving_cell"],
             "coupling_loss_db": m.data["coupling_loss_db"]}
            for m in log.decoded(NETWORK_UE) if m.data.get("UE_type") == "dropped"]


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
    reach = np.abs(sites - layout.center_m).max() + _cell_radius(s["layout"]) + 20.0
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="caviar-core calibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("model", choices=["38.901", "ray-traced"],
                        help="38.901: TR 38.901 phase 1; ray-traced: the ray-traced channel in --scene "
                             "beside 38.901 UMi on one 7-site layout")
    parser.add_argument("--scenario", default="UMa", help="UMa or UMi (Table 7.8-1)")
    parser.add_argument("--carrier", type=float, default=6e9, help="6e9, 30e9 or 70e9 (Hz)")
    parser.add_argument("--drops", type=int, default=20, help="drops of 570 UEs (default 20)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/calibration"))
    parser.add_argument("--reference", type=pathlib.Path,
                        default=COMPANIES,
                        help="the 3GPP companies' CDFs (JSON) to draw and compare with")
    parser.add_argument("--scene", default="blueprints/osm-city/scene/scene.xml",
                        help="ray-traced: the scene (a Mitsuba XML file, e.g. scene build's)")
    parser.add_argument("--center", default="auto",
                        help="ray-traced: X,Y of the centre site in the scene frame (m), or auto: the centre "
                             "nearest the scene's middle with every site in the open")
    parser.add_argument("--samples", type=int, default=100_000, help="ray-traced: rays per site and drop")
    parser.add_argument("--max-depth", type=int, default=2, help="ray-traced: reflections per path")
    args = parser.parse_args(argv)
    if args.model == "ray-traced":
        return _main_side_by_side(args)
    try:
        result = calibrate(args.scenario, args.carrier, args.drops, args.out, args.seed, args.reference)
    except CalibrationError as e:
        print(f"caviar-core calibrate: {e}", file=sys.stderr)
        return 2
    stem = f"{result['settings']['scenario']}-{args.carrier / 1e9:g}GHz"
    print(f"{result['samples']} UEs in {result['drops']} drops, {result['wall_s']} s: "
          f"{args.out / (stem + '.json')}, {args.out / (stem + '.png')}")
    for metric, rows in result.get("reference", {}).items():
        if isinstance(rows, dict):
            print(f"  {metric}: " + ", ".join(
                f"{p} {r['ours']:.1f} ({'in' if r['within_range'] else 'OUT of'} [{r['min']:.1f}, {r['max']:.1f}])"
                for p, r in rows.items()))
    return 0


def _main_side_by_side(args: argparse.Namespace) -> int:
    try:
        center = None
        if args.center != "auto":
            try:
                x, y = (float(v) for v in args.center.split(","))
            except ValueError:
                raise CalibrationError(f"--center: expected X,Y in metres or auto, got {args.center!r}") from None
            center = (x, y)
        result = side_by_side(args.scene, args.drops, args.out, center, args.seed, args.samples, args.max_depth)
    except CalibrationError as e:
        print(f"caviar-core calibrate: {e}", file=sys.stderr)
        return 2
    print(f"layout centred at {result['settings']['layout']['center_m']}: "
          f"{args.out / 'raytraced-vs-38.901-umi.json'}, {args.out / 'raytraced-vs-38.901-umi.png'}")
    for channel, r in result["channels"].items():
        print(f"  {channel}: {r['samples']} UEs ({r['uncovered']} reached by no cell), {r['wall_s']} s")
    for metric, d in result["difference_db"].items():
        print(f"  ray-traced − 38.901 {metric}: " + ", ".join(f"{p} {v:+.1f} dB" for p, v in d.items()))
    return 0
