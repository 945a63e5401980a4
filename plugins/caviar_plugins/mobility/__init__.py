"""Mobility: where the UEs are. Flights publish positions on ``3D.mobility.positions``
in the scene frame (:mod:`~caviar_plugins.mobility.frames`).

* :class:`WaypointFlight` (``waypoint-flight``): along waypoints, hovering on request.
* :class:`RandomWaypointFlight` (``random-waypoint-flight``): between random waypoints.
* :func:`read_waypoints`, :class:`Path`: waypoint files and the route through them.
"""

from caviar_plugins.mobility.frames import AIRSIM_NED_OFFSET, AIRSIM_NED_SIGN, airsim_ned_to_scene
from caviar_plugins.mobility.random_waypoint_flight import RandomWaypointFlight
from caviar_plugins.mobility.waypoint_flight import WaypointFlight
from caviar_plugins.mobility.waypoints import Path, read_waypoints

__all__ = ["AIRSIM_NED_OFFSET", "AIRSIM_NED_SIGN", "Path", "RandomWaypointFlight", "WaypointFlight",
           "airsim_ned_to_scene", "read_waypoints"]
