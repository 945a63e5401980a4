"""Road traffic from SUMO in lockstep with the engine: vehicles and pedestrians of an
OSM-built (or any) SUMO network, published in the scene frame every step.

* :class:`~caviar_plugins.traffic.plugin.SumoTraffic` — the ``sumo-traffic`` mobility plugin;
* :mod:`~caviar_plugins.traffic.demand` — random demand (randomTrips) for a network;
* :mod:`~caviar_plugins.traffic.sumo` — starting SUMO (libsumo in-process, or TraCI) and
  reading its vehicles and persons.
"""

from caviar_plugins.traffic.sumo import SumoError, ue_type_of

__all__ = ["SumoError", "ue_type_of"]
