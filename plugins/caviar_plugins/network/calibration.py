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
over the band of the 3GPP companies' curves where ``../shared/data``'s file has them
(``--reference``).
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="caviar-core calibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("model", choices=["38.901"], help="what to calibrate: TR 38.901 phase 1")
    parser.add_argument("--scenario", default="UMa", help="UMa or UMi (Table 7.8-1)")
    parser.add_argument("--carrier", type=float, default=6e9, help="6e9, 30e9 or 70e9 (Hz)")
    parser.add_argument("--drops", type=int, default=20, help="drops of 570 UEs (default 20)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/calibration"))
    parser.add_argument("--reference", type=pathlib.Path,
                        default=pathlib.Path("../shared/data/3gpp-calibration/phase1-uma-6ghz.json"),
                        help="the 3GPP companies' CDFs (JSON) to draw and compare with")
    args = parser.parse_args(argv)
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
