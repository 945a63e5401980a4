"""Plugins of the CAVIAR co-simulation, by domain.

* :mod:`~caviar_plugins.mobility`: flights (``waypoint-flight``, ``random-waypoint-flight``),
  waypoints and coordinate frames.
* :mod:`~caviar_plugins.radio`: communications (``sionna-link``, ``free-space-link``,
  ``link-monitor``), the ray-traced radio scene, beams and the link budget.
* :mod:`~caviar_plugins.vision`: ``camera``, ``image-link`` and ``person-detector``.
* :mod:`~caviar_plugins.beam_selection`: ``beam-selector`` and ``beam-dataset``.
* :mod:`~caviar_plugins.sar`: the search-and-rescue ``mission`` and its results table.
* :mod:`~caviar_plugins.schema`: the topics and the position payload they share.

Each plugin is a :class:`caviar.Plugin` that declares what it ``publishes``; none of them
knows how messages travel. Offline tools run with ``python -m``:
``caviar_plugins.beam_selection.train_tree``, ``caviar_plugins.vision.train_detector``,
``caviar_plugins.sar.results``.
"""

from caviar_plugins import schema
from caviar_plugins.assets import DATA, SCENES
from caviar_plugins.beam_selection import BeamDataset, BeamSelector
from caviar_plugins.mobility import RandomWaypointFlight, WaypointFlight
from caviar_plugins.radio import FreeSpaceLink, LinkMonitor, SionnaLink
from caviar_plugins.sar import Mission
from caviar_plugins.vision import Camera, ImageLink, PersonDetector

__all__ = ["DATA", "SCENES", "BeamDataset", "BeamSelector", "Camera", "FreeSpaceLink", "ImageLink", "LinkMonitor",
           "Mission", "PersonDetector", "RandomWaypointFlight", "SionnaLink", "WaypointFlight", "schema"]
