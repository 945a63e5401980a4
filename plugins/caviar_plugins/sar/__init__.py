"""The search-and-rescue use case of the paper.

* :class:`Mission` (``mission``): stops the UAV to upload its images on a detection and
  counts the rescued targets (``mission.*`` topics).
* ``python -m caviar_plugins.sar.results``: runs the SAR blueprint with random, tree and
  oracle beam selection and writes the paper's mission table.
"""

from caviar_plugins.sar.mission import Mission

__all__ = ["Mission"]
