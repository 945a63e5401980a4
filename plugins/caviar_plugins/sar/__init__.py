"""The search-and-rescue use case of the paper.

* :class:`Mission` (``mission``): stops the UAV to upload its images on a detection and
  counts the rescued targets (``mission.*`` topics).

Its results table (the SAR blueprint with random, tree and oracle beam selection) is made
offline by ``python -m caviar_plugins.tools.results.sar``.
"""

from caviar_plugins.sar.mission import Mission

__all__ = ["Mission"]
