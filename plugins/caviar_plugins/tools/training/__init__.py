"""The models the plugins load, trained offline (``python -m caviar_plugins.tools.training.X``).

* :mod:`~caviar_plugins.tools.training.train_tree`: the ``beam-selector``'s decision tree,
  from ``beam-dataset`` runs;
* :mod:`~caviar_plugins.tools.training.train_detector`: the ``person-detector``'s pixel
  classifier, on rendered frames;
* :mod:`~caviar_plugins.tools.training.twin_frames`: labelled frames for a YOLO, rendered
  by the twin; :mod:`~caviar_plugins.tools.training.train_yolo` trains the project's YOLO
  on them and :mod:`~caviar_plugins.tools.training.yolo_eval` scores detectors on the
  held-out ones.
"""
