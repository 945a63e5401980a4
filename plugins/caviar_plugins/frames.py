"""Coordinate frames.

The project's frame is the radio scene's: x east, y north, z up, metres, ground at
z = 0 (the Central Park scene of the paper). The paper's waypoints are AirSim NED
coordinates relative to AirSim's PlayerStart; the original CAVIAR code mapped them
to the scene with x = 23.34 + x_ned, y = -3.42 - y_ned, z = 137.23 - z_ned.
"""

from __future__ import annotations

import csv
import pathlib

import numpy as np

AIRSIM_NED_OFFSET = (23.34, -3.42, 137.23)
AIRSIM_NED_SIGN = (1.0, -1.0, -1.0)


def airsim_ned_to_scene(points, offset=AIRSIM_NED_OFFSET, sign=AIRSIM_NED_SIGN) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    return np.asarray(offset) + np.asarray(sign) * p


def read_waypoints(path: str | pathlib.Path) -> np.ndarray:
    """An (N, 3) array from a CSV file with a header row X,Y,Z."""
    path = pathlib.Path(path)
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows or [h.strip().upper() for h in rows[0]] != ["X", "Y", "Z"]:
        raise ValueError(f"{path}: expected a header row 'X,Y,Z'")
    try:
        pts = np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=float)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise ValueError(f"{path}: expected at least two rows of three numbers")
    return pts
