"""Radio: the communications between the base station and the UEs.

* :class:`SionnaLink` (``sionna-link``): Sionna RT ray tracing in the loop, on a
  :class:`RadioScene` (:mod:`~caviar_plugins.radio.scene`, which knows nothing of caviar; a
  client of :mod:`caviar_plugins.rt`, the home of ray tracing).
* :class:`FreeSpaceLink` (``free-space-link``): Friis free space, the quickstart's stand-in.
* :class:`LinkMonitor` (``link-monitor``): throughput per UE to a CSV file and a plot.
* :mod:`~caviar_plugins.radio.beams` (DFT codebooks, beam-pair gains) and
  :mod:`~caviar_plugins.radio.link_budget` (SINR, Shannon throughput, Friis).
"""

from caviar_plugins.radio.beams import beam_gains, dft_codebook, element_grid, pair_index, split_pair
from caviar_plugins.radio.free_space_link import FreeSpaceLink
from caviar_plugins.radio.link_budget import BOLTZMANN, SPEED_OF_LIGHT, LinkBudget, friis_path_gain
from caviar_plugins.radio.link_monitor import LinkMonitor
from caviar_plugins.radio.scene import UAV_BODY, Link, RadioConfig, RadioScene
from caviar_plugins.radio.sionna_link import SionnaLink, SionnaLinkParams

__all__ = ["BOLTZMANN", "SPEED_OF_LIGHT", "UAV_BODY", "FreeSpaceLink", "Link", "LinkBudget", "LinkMonitor",
           "RadioConfig", "RadioScene", "SionnaLink", "SionnaLinkParams", "beam_gains", "dft_codebook",
           "element_grid", "friis_path_gain", "pair_index", "split_pair"]
