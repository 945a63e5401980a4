"""The topics the plugins exchange and the payloads they share: the paper's schema in
one place.

Topic names are the paper's where it has them (``3D.mobility.positions``,
``communications.throughput``, ``communications.state``). A per-UE topic is a prefix
followed by the UE's id (``3D.camera.uav1``): :func:`per_ue` builds it, :func:`every_ue`
is the pattern that matches it for every UE and :func:`ue_of` reads the id back.

A position payload (paper schema)::

    {"UE_type": "UAV", "UE_Id": "uav1", "position": {"x": 1.0, "y": 2.0, "z": 3.0}}

in metres, in the scene frame (x east, y north, z up); :func:`position_payload` builds
one and :func:`read_position` reads its coordinates.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

# Mobility and the 3D scene
POSITIONS = "3D.mobility.positions"
"""Where a UE is: a position payload (see :func:`position_payload`)."""
DEPARTED = "3D.mobility.departed"
"""A UE entered the scene (a SUMO vehicle or person departed): ``{"UE_type", "UE_Id"}``."""
ARRIVED = "3D.mobility.arrived"
"""A UE left the scene (arrived at its destination): ``{"UE_type", "UE_Id"}``."""
TRAFFIC = "3D.mobility.traffic"
"""Once a step from the traffic simulator: ``{"sumo_time", "vehicles", "persons", "departed", "arrived"}``,
``sumo_time`` being the simulator's own clock (equal to the engine's)."""
FORECAST = "3D.mobility.forecast"
"""Where a UE expects to be next (opt-in, e.g. waypoint-flight's ``forecast_steps``):
``{"UE_type", "UE_Id", "ts", "positions": [{"x", "y", "z"}, …]}``, the positions at the
next steps (one per ``ts``), assuming no new command (hover) arrives."""
LIDAR = "3D.lidar"
"""Prefix: ``3D.lidar.<UE_Id>`` one LiDAR sweep's point cloud (float32, n × 6: x, y, z,
intensity, ring, object; binary); ``3D.lidar.<UE_Id>.sweep`` its metadata: ``{"UE_Id",
"sweep", "time", "origin", "rays", "points", "dropped", "columns", "objects"}``
(:mod:`caviar_plugins.lidar`)."""
CAMERA = "3D.camera"
"""Prefix: ``3D.camera.<UE_Id>`` a nadir camera image (uint8, H × W × 3, binary);
``3D.camera.<UE_Id>.file`` the same image as a PNG artifact; ``3D.camera.<UE_Id>.depth`` its
depth image (float32, H × W, metres from the camera, NaN where only sky; ``depth = true``)."""

# A live twin: telemetry from real vehicles (caviar_plugins.live)
LIVE_TELEMETRY = "live.telemetry"
"""Per step, from a telemetry plugin (``mavlink-telemetry``): where it listens, its counts
(received, late, out of order, missing, garbage, ...; see
:data:`caviar_plugins.live.telemetry.COUNTS`), per UE ``{"UE_Id", "sysid", "age_s",
"stale", "positions"}`` and the warnings of the step."""

# Communications
THROUGHPUT = "communications.throughput"
"""``{"UE_type", "UE_Id", "throughput"}``, Mbit/s (see :func:`throughput_payload`)."""
STATE = "communications.state"
"""``"Ready"`` once a step's communications results are out."""
LINK = "communications.link"
"""Ray-traced link details per UE: LOS flag, best and used beam pair, path gain, SNR."""
CHANNEL = "communications.channel"
"""Prefix: ``communications.channel.<UE_Id>`` the MIMO channel H (complex64, binary)."""
PREDICTION = "communications.prediction"
"""Per UE and step, the link predicted at horizons ahead (``sionna-link``'s
``predict_horizons_s``): ``{"UE_type", "UE_Id", "time", "predictions": [{"horizon_s",
"at_s", "source", "position", "path_gain_db", "los", "best_pair", "best_throughput"}]}``
(:mod:`caviar_plugins.radio.prediction`)."""
BEAM_GAINS = "communications.beam_gains"
"""Prefix: ``communications.beam_gains.<UE_Id>`` gains of all beam pairs (float32, binary)."""
PATHS = "communications.paths"
"""Prefix: ``communications.paths.<UE_Id>`` the UE's ray-traced paths of the step (``sionna-link``'s
``publish_paths``): per path the coefficient, delay, angles of departure and arrival, interaction
types and points, with the tx/rx positions and the link's settings; binary, an ``.npz`` archive
(:class:`caviar_plugins.radio.path_data.PathData`, ``PathData.from_bytes(message.data)``)."""

# The radio network (several cells; caviar_plugins.network)
NETWORK_UE = "network.ue"
"""Per UE and step: ``{"UE_type", "UE_Id", "serving_cell", "sinr_db", "sir_db",
"coupling_loss_db", "rsrp_dbm": {cell: dBm}, "throughput_mbps"}``, ``"position_m"`` for a UE
the network's layout dropped, and, with the Sionna SYS link model, ``"mcs", "tbler",
"harq_ack", "harq_nack", "prbs"`` (over the step's slots); with SSB beams (``beams``),
``"ssb_beam", "beam_azimuth_deg", "beam_elevation_deg"``: the serving beam and where it points; with
the uplink (``uplink``), ``"ul_tx_power_dbm", "ul_sinr_db", "ul_throughput_mbps", "ul_mcs", "ul_tbler"...``;
with a load (``traffic``), ``"dl_queue_bytes"`` and ``"ul_queue_bytes"``: the bytes waiting (none for a
full buffer). With a load the throughputs count the queues' bytes delivered, not padding."""
NETWORK_UES = "network.ues"
"""Per step, with ``ue_reports = "table"``: every UE's ``network.ue`` fields as one table (a
``polars.DataFrame``, recorded in Arrow's format), a column a field and a row a UE:
``UE_Id``, ``UE_type``, ``serving_cell``, ..., ``rsrp_dbm`` (a struct, a field a cell by its
name); null where a UE's ``network.ue`` would hold None or leave the field out
(:func:`caviar_plugins.network.ues.table_rows` turns the table back into those reports)."""
NETWORK_EVENTS = "network.events"
"""``{"event": "attach" | "handover" | "rlf", "UE_Id", "time", "to_cell", "rsrp_to_dbm"}``
(and ``"from_cell", "rsrp_from_dbm"`` for a handover or a radio-link failure)."""
NETWORK_RADIO_MAP = "network.radio_map"
"""The best-server SINR map (``radio-map.npz``, ``radio-map.png``, ``radio-map-layer.png``),
artifacts at the first step."""
VIEW_RADIO_MAP = "view.radio_map"
"""The map's SINR layer for the browser view (a ``view.*`` ``images`` entry), at the first step."""
VIEW_LIDAR = "view.lidar"
"""A LiDAR's last sweep of the step for the browser view (``view.*`` ``points``, thinned to
``view_points``, coloured by what they hit)."""
VIEW_ENERGY = "view.energy"
"""Each UAV's state of charge for the browser view (``view.*`` ``labels`` beside the UAV)."""
NS3_LINK = "network.ns3.link"
"""Per UE and step, from ``ns3-network``: ``{"UE_Id", "time", "ran", "loss_db" (the loss set
in ns-3 from the channel), "delivered_bytes", "throughput_mbps" (at the ground station),
"sinr_db", "mcs", "grants", "tb_bytes"}``, the last four what the eNB saw of the uplink (LTE:
mean SRS SINR, mean granted MCS; None on point-to-point)."""
NETWORK_TRANSFERS = "network.transfers"
"""Per completed file or carried message (the radio network's ``traffic``): ``{"UE_Id",
"direction", "source" ("ftp" or the message's topic), "bytes", "queued_s", "delivered_s",
"delay_s", "upt_mbps"}`` (``"lost": true`` and no ``delivered_s`` for one its UE left
unfinished)."""
NETWORK_CELLS = "network.cells"
"""Per step: ``{"cells": [{"cell", "ues", "active_share"}]}``, the UEs a cell serves and the
share of the step's slots in which it scheduled someone."""

# AI
BEAM_SELECTION = "ai.beam.selection"
"""``{"UE_Id", "beam_pair"}``: the pair the communications module should use."""
IMAGES = "ai.images"
"""Prefix: ``ai.images.<UE_Id>`` a camera image as received over the UE's link."""
IMAGE_QUALITY = "ai.image_quality"
"""``{"UE_Id", "throughput", "loss_rate", "psnr_db", "step"}`` per image sent; over ns-3
(``ns3-network``) also ``"image", "network", "sent_at", "released_at", "complete",
"delay_s", "bytes_sent", "bytes_received", "packets_sent", "packets_lost"``."""
DETECTIONS = "ai.detections"
"""``{"UE_Id", "image_step", "count", "detections"}``; a detection may carry ``ground``
``{"x", "y"}``, its estimated position on the ground."""
LINK_REPORT = "ai.link.report"
"""The link monitor's throughput CSV and plot (artifacts)."""

# The search-and-rescue mission
HOVER = "mission.hover"
"""``{"UE_Id", "seconds"}``: the UAV stops for this long."""
UPLOAD = "mission.upload"
"""``{"UE_Id", "bytes", "rescue"}``: the images of a rescue, for the network to carry uplink
(the mission's ``upload = "network"``)."""
RESCUE = "mission.rescue"
"""One rescued target: ``{"UE_Id", "x", "y", "time", "throughput", "hover_s"}``."""
RESULT = "mission.result"
"""At the end: ``{"mission_time_s", "rescued", "rescues"}`` and, with ``uav.energy``,
``"energy"`` (per UAV: Wh used, state of charge, returned home) and ``"energy_per_rescue_wh"``."""
RETURN_HOME = "mission.return"
"""``{"UE_Id", "speed_mps", "home", "reason"}``: the UAV leaves its route and flies straight
home ([x, y, z], ``uav.energy``'s: where the UAV was first seen or its ``home`` parameter) at
this speed, and the episode ends there."""

# UAV energy (caviar_plugins.energy)
ENERGY = "uav.energy"
"""Per UAV and step (:class:`caviar_plugins.energy.UavEnergy`): ``{"UE_type", "UE_Id",
"speed_mps", "power_w", "propulsion_w", "energy_wh", "remaining_wh", "soc", "capacity_wh", "reserve_wh",
"home", "return_wh", "return_speed_mps", "must_return"}``: the power over the last step
(propulsion, communication and computing), the energy used since the start, the battery
left, and the energy to fly home at ``return_speed_mps``."""

# The self-calibrating twin (caviar_plugins.twin)
MEASUREMENTS = "measurements"
"""Prefix: ``measurements.<UE_Id>`` a vehicle's radio measurements, one sample or
``{"samples": [...]}`` (:mod:`caviar_plugins.twin.measurements` names the fields)."""
MATERIALS = "twin.materials"
"""``{"time", "materials": {material: {property: value}}}``: the twin's learned radio
materials, which the ray-traced links apply from then on."""
TWIN_FIT = "twin.fit"
"""Per step with new measurements ``{"time", "samples", "new", "prediction_error_db"}`` (the
new samples as the twin predicted them before learning from them), and per refit ``{"time",
"samples", "refit", "rmse_db", "learned", "not_identifiable", "confounded", "ambiguous"}``
(``confounded``: per learned property, the fixed ones whose effect it cannot be told from;
``ambiguous``: per property, the other values that fit as well)."""

# Datasets
DATASET_RECORD = "dataset.record"
"""A record written by a dataset module (artifact)."""


UE_TYPES = ("UAV", "car", "vehicle", "pedestrian", "bus", "truck", "motorcycle", "bicycle", "tram", "train",
            "emergency", "dropped")
"""The ``UE_type`` of the positions the shipped modules publish: ``UAV`` (waypoint-flight,
mavlink-telemetry's default), SUMO's by vehicle class (``car``, ``bus``..., ``pedestrian``:
:data:`caviar_plugins.traffic.sumo.UE_TYPES`) and ``dropped`` (a UE a radio network's layout
dropped). A setting that names another type warns (a module of the user's may publish it)."""


def _view_contract():
    """What the browser view draws of these topics (registered in group ``caviar.view``)."""
    from caviar.view.contract import ViewContract
    from caviar_plugins.assets import SCENES

    return ViewContract(
        positions=(POSITIONS,), throughput=(THROUGHPUT,), link=(LINK,),
        frame_prefixes=(CAMERA + ".", IMAGES + "."),
        event_prefixes=("mission.",), event_topics=(DETECTIONS, NETWORK_EVENTS),
        event_requires=((DETECTIONS, "count"),),
        # The paper's rooftop base station in Central Park: free-space-link's and
        # sionna-link's default tx_position.
        default_transmitters=(("free-space-link", (-154.0, 64.0, 120.0)), ("sionna-link", (-154.0, 64.0, 120.0))),
        scene_dirs=(str(SCENES),), default_scene="central_park")


def __getattr__(name: str):
    # ``VIEW``: the paper's topics as the browser view draws them (a
    # caviar.view.contract.ViewContract), made when the view asks for it, so that a plugin
    # importing its topic names does not import the view.
    if name == "VIEW":
        return _view_contract()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def per_ue(prefix: str, ue_id: str) -> str:
    """The per-UE topic ``PREFIX.UE_Id``."""
    return f"{prefix}.{ue_id}"


def every_ue(prefix: str) -> str:
    """The pattern matching ``PREFIX.UE_Id`` for every UE."""
    return f"{prefix}.*"


def ue_of(topic: str) -> str:
    """The UE's id in a per-UE topic (its last token)."""
    return topic.rsplit(".", 1)[-1]


def position_payload(ue_id: str, xyz: Sequence[float] | np.ndarray, ue_type: str = "UAV") -> dict[str, Any]:
    """The paper's position payload of a UE at ``xyz`` (metres, scene frame)."""
    x, y, z = (float(v) for v in xyz)
    return {"UE_type": ue_type, "UE_Id": ue_id, "position": {"x": x, "y": y, "z": z}}


def read_position(payload: Mapping[str, Any]) -> np.ndarray:
    """The coordinates (x, y, z) of a position payload, as a float array of shape (3,)."""
    p = payload["position"]
    return np.array([p["x"], p["y"], p["z"]], dtype=float)


def throughput_payload(ue_type: str, ue_id: str, mbps: float | np.floating | np.ndarray) -> dict[str, Any]:
    """The paper's throughput payload (Mbit/s)."""
    return {"UE_type": ue_type, "UE_Id": ue_id, "throughput": float(mbps)}


PAYLOAD_FIELDS: dict[str, tuple[str, ...] | None] = {
    UPLOAD: ("UE_Id", "bytes", "rescue"), THROUGHPUT: ("UE_type", "UE_Id", "throughput"),
    per_ue(CAMERA, "uav1"): None, per_ue(LIDAR, "uav1"): None, per_ue(IMAGES, "uav1"): None,
    per_ue(CHANNEL, "uav1"): None, per_ue(BEAM_GAINS, "uav1"): None, per_ue(PATHS, "uav1"): None,
}
"""The fields of the JSON payloads of a few topics above, and (None) topics whose payloads are
binary (an array, a byte string: no fields), a per-UE topic by one UE's: what a setting that
names a payload field (``traffic.carry``'s ``size_field``) is checked against before a run."""


def fields_of(pattern: str) -> dict[str, tuple[str, ...] | None]:
    """The topics of :data:`PAYLOAD_FIELDS` that ``pattern`` matches, with their fields."""
    from caviar.topics import matches

    return {topic: fields for topic, fields in PAYLOAD_FIELDS.items() if matches(pattern, topic)}
