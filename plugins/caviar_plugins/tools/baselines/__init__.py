"""Beam selection compared on the same flights (``python -m caviar_plugins.tools.baselines.X``).

* :mod:`~caviar_plugins.tools.baselines.gym_baseline`: an agent trained in the Gymnasium
  environment against the tree, random and oracle selection;
* :mod:`~caviar_plugins.tools.baselines.paper_topk`: the paper's top-K table under
  ``protocol = "paper"``;
* :mod:`~caviar_plugins.tools.baselines.lidar_selector`: LiDAR-aided selection (a CNN on
  the occupancy grid) against position-only selection.
"""
