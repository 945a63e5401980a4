"""What the calibration runs: TR 38.901 Table 7.8-1's settings per scenario and carrier, the
layout of the ray-traced side-by-side, and the configurations (TOML) both write for the
``radio-network`` plugin."""

from __future__ import annotations

import json
import pathlib
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
SPEC_VERSION = "16.1"
"""The release of TR 38.901 the calibration runs by default: the companies' curves (2016) were made
with TR 38.900 V14.0.0, whose O2I high-loss model Sionna's ``16.1`` tables keep (see
:data:`~caviar_plugins.network.tr38901.SPEC_VERSIONS`)."""
METRICS = ("coupling_loss_db", "geometry_sinr_db", "wideband_sir_db")
# The companies' file names these metrics so (coupling loss as a gain there).
REFERENCE_NAMES = {"coupling_loss_db": "coupling_loss", "geometry_sinr_db": "geometry_sinr",
                   "wideband_sir_db": "wideband_sir"}
PERCENTILES = list(range(101))
COMPANIES = DATA / "3gpp-phase1.json"
"""The 20 companies' phase-1 CDFs of the six cases, UMa and UMi at 6, 30 and 70 GHz
(R1-165974; ``Phase1Calibration_v42_CMCC.xlsx`` as NVIDIA Aerial encodes it: the file's
``provenance`` says where from), shipped with the package: the band the calibration is drawn
over."""


class CalibrationError(ValueError):
    """A scenario or carrier Table 7.8-1 does not define."""


def settings(scenario: str, carrier_hz: float, spec_version: str = SPEC_VERSION) -> dict[str, Any]:
    """Table 7.8-1's settings of ``scenario`` (``UMa``, ``UMi``) at ``carrier_hz``, with the
    38.901 channel's tables of release ``spec_version``."""
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
            "o2i_high_loss_share": 0.5, "spec_version": spec_version, "ue_antenna": "omni, 0 dBi", "fast_fading": False,
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
analysis = ["communications.throughput", "network.ues", "network.events", "network.cells",
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
ue_reports = "table"
layout = {{ {layout} }}
column = {{ {column} }}
tr38901 = {{ o2i_high_loss_share = {s['o2i_high_loss_share']}, spec_version = "{s['spec_version']}" }}
handover = {{ offset_db = 0.0, hysteresis_db = 0.0, l3_filter_k = 0.0, min_rsrp_dbm = -1000.0 }}
"""


# --- ray-traced against stochastic on one layout -------------------------------------------

SIDE_BY_SIDE_LAYOUT = {"kind": "hex", "rings": 1, "isd_m": 200.0, "height_m": 10.0, "min_distance_m": 10.0,
                       "wraparound": False, "indoor_share": 0.0, "ues_per_sector": UES_PER_SECTOR,
                       "redrop": "every-step"}
"""The UMi-like layout both channels run on: 7 sites × 3 sectors at ISD 200 m, 10 m high,
outdoor UEs (the ray tracer has no building entry loss), no wraparound (a scene does not
repeat)."""
SIDE_BY_SIDE_CHANNELS = ("ray-traced", "38.901-umi")


def cell_radius(layout: dict[str, Any]) -> float:
    """A hexagonal cell's radius (its corner from the site) at the layout's ISD."""
    return float(layout["isd_m"]) / np.sqrt(3)


def side_by_side_toml(s: dict[str, Any], channel: str, drops: int, seed: int, scene_file: pathlib.Path) -> str:
    """The calibration's configuration with ``channel`` on the side-by-side layout."""
    text = config_toml(s, drops, seed)
    text = text.replace(f'channel = "38.901-{s["scenario"].lower()}"', f'channel = "{channel}"')
    if channel == "ray-traced":
        rt = s["raytracing"]
        text += (f'scene = {json.dumps(str(scene_file))}\n'
                 f'raytracing = {{ max_depth = {rt["max_depth"]}, samples_per_src = {rt["samples_per_src"]}, '
                 f'diffraction = true, threads = {rt["threads"]} }}\n'
                 'evolution = { mode = "hold" }\n')
    return text
