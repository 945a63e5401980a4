"""Files shipped with the plugins (package data, see ``plugins/pyproject.toml``)."""

import pathlib

DATA = pathlib.Path(__file__).parent / "data"
"""The paper's UAV waypoints (CSV files with a header row X,Y,Z)."""
SCENES = pathlib.Path(__file__).parent / "scenes"
"""3D scenes, one folder each (``central_park/central_park.xml`` and its meshes), shared
by the radio and the camera."""
