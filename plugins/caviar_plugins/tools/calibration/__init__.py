"""``caviar-core calibrate``: TR 38.901's phase-1 calibration, and the ray-traced channel
beside 38.901 UMi, run through the ``radio-network`` plugin as every blueprint runs.

* :mod:`~caviar_plugins.tools.calibration.config`: Table 7.8-1's settings and the
  configurations the runs write;
* :mod:`~caviar_plugins.tools.calibration.runs`: the runs and what they measure
  (:func:`calibrate`, :func:`side_by_side`);
* :mod:`~caviar_plugins.tools.calibration.plots`: their figures;
* :mod:`~caviar_plugins.tools.calibration.cli`: the command (:func:`main`).
"""

from caviar_plugins.tools.calibration.cli import main
from caviar_plugins.tools.calibration.config import (
    COMPANIES,
    METRICS,
    PERCENTILES,
    CalibrationError,
    config_toml,
    settings,
    side_by_side_toml,
)
from caviar_plugins.tools.calibration.runs import calibrate, find_center, side_by_side

__all__ = ["COMPANIES", "METRICS", "PERCENTILES", "CalibrationError", "calibrate", "config_toml", "find_center",
           "main", "settings", "side_by_side", "side_by_side_toml"]
