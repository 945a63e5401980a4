"""Beam selection: the AI that picks the beam pair, and the dataset it learns from.

* :class:`BeamSelector` (``beam-selector``): a decision tree on the UAV position, or the
  random and oracle baselines, publishing ``ai.beam.selection``.
* :class:`BeamDataset` (``beam-dataset``): one npz record per UAV and step (position,
  best pair, LOS, gains of all pairs); :func:`load` reads a run's records.
* :mod:`~caviar_plugins.beam_selection.decision_tree`: fitting and scoring the tree;
  ``python -m caviar_plugins.tools.training.train_tree`` trains it on dataset runs.
"""

from caviar_plugins.beam_selection.dataset import BeamDataset, load
from caviar_plugins.beam_selection.decision_tree import K_VALUES, full_scores, load_tree, save, top_k_accuracy, train
from caviar_plugins.beam_selection.selector import METHODS, BeamSelector

__all__ = ["K_VALUES", "METHODS", "BeamDataset", "BeamSelector", "full_scores", "load", "load_tree", "save",
           "top_k_accuracy", "train"]
