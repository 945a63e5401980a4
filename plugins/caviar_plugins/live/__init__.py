"""A live twin: real vehicles (or their simulators) in the loop.

* :class:`~caviar_plugins.live.mavlink_telemetry.MavlinkTelemetry` (``mavlink-telemetry``):
  positions from MAVLink (PX4, ArduPilot) over UDP on ``3D.mobility.positions``, with
  the link's health on ``live.telemetry``;
* :mod:`~caviar_plugins.live.telemetry`: the MAVLink decoder and its counts, the UDP reader;
* :mod:`~caviar_plugins.live.geo`: geodetic coordinates to the scene frame.

Needs the ``live`` extra (pymavlink): ``pip install 'caviar-plugins[live]'``.
"""
