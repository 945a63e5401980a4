"""Offline tools above the plugins: commands that run before or after a simulation, never
inside one. They may import any runtime package of :mod:`caviar_plugins`; no runtime package
imports them, and none of those uses argparse (``tests/test_layers.py`` checks both).

* :mod:`~caviar_plugins.tools.export`: ``caviar-core export`` (a recorded run as a DeepMIMO
  scenario or as Raymobtime's files);
* :mod:`~caviar_plugins.tools.scene`: ``caviar-core scene`` (a scene and a road network
  from OpenStreetMap, built by :mod:`caviar_plugins.osm`);
* :mod:`~caviar_plugins.tools.calibration`: ``caviar-core calibrate`` (TR 38.901 phase 1,
  and the ray-traced channel beside 38.901 UMi);
* :mod:`~caviar_plugins.tools.training`: the models the plugins load (the beam-selection
  tree, the pixel person detector, the YOLO and its labelled frames);
* :mod:`~caviar_plugins.tools.baselines`: beam selection compared (the Gymnasium agent, the
  paper's top-K table, the LiDAR CNN);
* :mod:`~caviar_plugins.tools.results`: the result tables of docs/results (the SAR mission,
  the image degradation, the physical-protocol set).
"""
