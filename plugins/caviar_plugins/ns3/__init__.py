"""End to end over a real network stack: the ``ns3-network`` plugin runs ns-3 (PyPI's
``ns3`` wheel) in lockstep with the engine, sets its links' losses from the ray tracer
and carries the UAVs' camera images as packets to the ground station.

- :mod:`~caviar_plugins.ns3.native`: loading ns-3, and calls into it that cannot end the
  process (an abort inside becomes an exception with ns-3's words);
- :mod:`~caviar_plugins.ns3.checks`: every ns-3 setting checked against what ns-3 accepts;
- :mod:`~caviar_plugins.ns3.simulator`: one ns-3 network advanced step by step;
- :mod:`~caviar_plugins.ns3.plugin`: the plugin;
- :mod:`~caviar_plugins.ns3.report`: its figures for ``caviar-core report``.
"""
