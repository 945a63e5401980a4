"""Plugins of the CAVIAR co-simulation.

Each module is a :class:`caviar.Plugin`; none of them knows how messages travel.
"""

import pathlib

DATA = pathlib.Path(__file__).parent / "data"
"""Data shipped with the plugins (the paper's UAV waypoints)."""
