"""End to end over a real network stack: the ``ns3-network`` plugin runs ns-3 (PyPI's
``ns3`` wheel) in lockstep with the engine, sets its links' losses from the ray tracer
and carries the UAVs' camera images as packets to the ground station.

- :mod:`~caviar_plugins.ns3.simulator`: one ns-3 network advanced step by step;
- :mod:`~caviar_plugins.ns3.plugin`: the plugin;
- :mod:`~caviar_plugins.ns3.report`: its figures for ``caviar-core report``.
"""
