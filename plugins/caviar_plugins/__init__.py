"""Plugins of the CAVIAR co-simulation, by domain.

Every plugin this package registers (entry points of group ``caviar.plugins``, the names a
configuration's ``plugin = "..."`` gives), by subpackage:

* :mod:`~caviar_plugins.mobility`: ``waypoint-flight`` (:class:`WaypointFlight`),
  ``random-waypoint-flight`` (:class:`RandomWaypointFlight`); waypoints and coordinate frames.
* :mod:`~caviar_plugins.radio`: ``sionna-link`` (:class:`SionnaLink`), ``free-space-link``
  (:class:`FreeSpaceLink`), ``link-monitor`` (:class:`LinkMonitor`); the ray-traced radio
  scene, beams, the link budget and the link level (Sionna SYS).
* :mod:`~caviar_plugins.vision`: ``camera`` (:class:`Camera`), ``image-link``
  (:class:`ImageLink`), ``person-detector`` (:class:`PersonDetector`).
* :mod:`~caviar_plugins.beam_selection`: ``beam-selector`` (:class:`BeamSelector`),
  ``beam-dataset`` (:class:`BeamDataset`).
* :mod:`~caviar_plugins.sar`: ``mission`` (:class:`Mission`), the search-and-rescue mission.
* :mod:`~caviar_plugins.traffic`: ``sumo-traffic`` (:class:`SumoTraffic`), SUMO in the loop,
  and ``sionna-traffic-link`` (:class:`SionnaTrafficLink`), its vehicles as UEs and as moving
  scatterers.
* :mod:`~caviar_plugins.network`: ``radio-network`` (:class:`RadioNetwork`), cells,
  interference, handover and scheduling.
* :mod:`~caviar_plugins.live`: ``mavlink-telemetry`` (:class:`MavlinkTelemetry`), a real
  vehicle's positions over MAVLink.
* :mod:`~caviar_plugins.energy`: ``uav-energy`` (:class:`UavEnergy`), every UAV's power,
  energy and battery (Zeng et al.'s rotary-wing model).
* :mod:`~caviar_plugins.lidar`: ``lidar`` (:class:`Lidar`), rotating LiDARs cast into the ray
  tracer's scene with the moving bodies.
* :mod:`~caviar_plugins.ns3`: ``ns3-network`` (:class:`Ns3Network`), the UAVs' images over the
  real ns-3 (LTE with its EPC, or point-to-point) in lockstep with the engine.
* :mod:`~caviar_plugins.twin`: ``scene-fitter`` (:class:`SceneFitter`), the twin's radio
  materials learned from measurements while a run goes (differentiable ray tracing), and
  ``measurement-emulator`` (:class:`MeasurementEmulator`), a stand-in for a vehicle's
  measurements.

Besides: :mod:`~caviar_plugins.rt`, ray tracing in one home (Sionna RT scene, path solver,
shoot cache, the adapter to Sionna's internals); :mod:`~caviar_plugins.osm`, scenes from
OpenStreetMap; :mod:`~caviar_plugins.schema`, the topics and the payloads they share.

Each plugin is a :class:`caviar.Plugin` that declares what it ``publishes``; none of them
knows how messages travel. The five of SUMO, the network, MAVLink and ns-3 are imported on
first use (``caviar_plugins.SumoTraffic``): their packages are optional extras.

Offline tools live above the plugins, in :mod:`~caviar_plugins.tools`, which no plugin
imports: the commands ``caviar-core export``, ``scene``, ``calibrate`` and ``fit-scene``, and, with
``python -m``, training (``caviar_plugins.tools.training.train_tree``,
``caviar_plugins.tools.training.train_detector``), baselines and result tables
(``caviar_plugins.tools.results.sar``).
"""

import importlib
from typing import Any

from caviar_plugins import schema
from caviar_plugins.assets import DATA, SCENES
from caviar_plugins.beam_selection import BeamDataset, BeamSelector
from caviar_plugins.energy import UavEnergy
from caviar_plugins.lidar import Lidar
from caviar_plugins.mobility import RandomWaypointFlight, WaypointFlight
from caviar_plugins.radio import FreeSpaceLink, LinkMonitor, SionnaLink
from caviar_plugins.sar import Mission
from caviar_plugins.vision import Camera, ImageLink, PersonDetector

_ON_FIRST_USE = {"SumoTraffic": "caviar_plugins.traffic.plugin", "SionnaTrafficLink": "caviar_plugins.traffic.link",
                 "RadioNetwork": "caviar_plugins.network.plugin",
                 "MavlinkTelemetry": "caviar_plugins.live.mavlink_telemetry",
                 "Ns3Network": "caviar_plugins.ns3.plugin", "SceneFitter": "caviar_plugins.twin.plugin",
                 "MeasurementEmulator": "caviar_plugins.twin.plugin"}


def __getattr__(name: str) -> Any:
    if name in _ON_FIRST_USE:
        return getattr(importlib.import_module(_ON_FIRST_USE[name]), name)
    raise AttributeError(f"module 'caviar_plugins' has no attribute {name!r}")


__all__ = ["DATA", "SCENES", "BeamDataset", "BeamSelector", "Camera", "FreeSpaceLink", "ImageLink", "Lidar",
           "LinkMonitor", "MavlinkTelemetry", "MeasurementEmulator", "Mission", "Ns3Network", "PersonDetector",
           "RadioNetwork", "RandomWaypointFlight", "SceneFitter", "SionnaLink", "SionnaTrafficLink", "SumoTraffic",
           "UavEnergy", "WaypointFlight", "schema"]
