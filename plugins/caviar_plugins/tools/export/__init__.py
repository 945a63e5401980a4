"""``caviar-core export``: a recorded run in another tool's format.

* :mod:`~caviar_plugins.tools.export.cli`: the command;
* :mod:`~caviar_plugins.tools.export.deepmimo_export`: a DeepMIMO v4 scenario from a
  ray-traced run's path data;
* :mod:`~caviar_plugins.tools.export.raymobtime`: a ``beam-dataset`` run in Raymobtime's
  files (and the LiDAR occupancy grid they hold).
"""
