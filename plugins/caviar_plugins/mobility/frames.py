"""Coordinate frames.

The project's frame is the radio scene's: x east, y north, z up, metres, ground at
z = 0 (the Central Park scene of the paper). The paper's waypoints are AirSim NED
coordinates relative to AirSim's PlayerStart; the original CAVIAR code mapped them
to the scene with x = 23.34 + x_ned, y = -3.42 - y_ned, z = 137.23 - z_ned.
"""

from __future__ import annotations

import numpy as np

AIRSIM_NED_OFFSET = (23.34, -3.42, 137.23)
AIRSIM_NED_SIGN = (1.0, -1.0, -1.0)


def airsim_ned_to_scene(points, offset=AIRSIM_NED_OFFSET, sign=AIRSIM_NED_SIGN) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    return np.asarray(offset) + np.asarray(sign) * p
