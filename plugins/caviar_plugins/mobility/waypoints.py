"""Waypoints and the route through them: CSV files of X,Y,Z rows and a polyline walked
at constant speed."""

from __future__ import annotations

import csv
import pathlib

import numpy as np


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


class Path:
    """A polyline walked at constant speed, parametrised by arc length."""

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=float)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def at(self, s: float) -> np.ndarray:
        s = min(max(s, 0.0), self.length)
        i = int(np.searchsorted(self.cum, s, side="right") - 1)
        i = min(i, len(self.points) - 2)
        seg = self.cum[i + 1] - self.cum[i]
        f = 0.0 if seg == 0 else (s - self.cum[i]) / seg
        return self.points[i] + f * (self.points[i + 1] - self.points[i])
