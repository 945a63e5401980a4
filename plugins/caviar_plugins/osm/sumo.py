"""A SUMO road network in the scene frame: the highway ways that touch the bbox (with
all their nodes) go to an OSM XML file, which netconvert (eclipse-sumo) converts with
the scene's PROJ string and no offset (``--offset.disable-normalization``), so net
coordinates are scene coordinates. Sidewalks and crossings are guessed.

Only ways at street level go in: the scene has no tunnels, floors or indoor spaces,
so underground ways (``tunnel=yes|culvert``, ``layer`` < 0, ``location=underground``),
indoor ways (``indoor=yes``, ``highway=corridor``) and ways on other levels (``level``
other than 0) are left out. Building passages (``tunnel=building_passage``) stay.

The build checks the frame: every junction named after an OSM node must lie within
0.1 m of that node's projection.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import xml.etree.ElementTree as ET

import numpy as np

from caviar_plugins.osm import BuildError
from caviar_plugins.osm.frame import BBox, Frame
from caviar_plugins.osm.reader import OsmData, Way

NETCONVERT_OPTIONS = [
    "--sidewalks.guess", "true", "--crossings.guess", "true",
    "--geometry.remove", "true", "--roundabouts.guess", "true", "--ramps.guess", "true",
    "--tls.guess-signals", "true", "--tls.discard-simple", "true", "--tls.join", "true",
    "--output.street-names", "true", "--output.original-names", "true",
]


def netconvert_binary() -> str:
    try:
        import sumo

        exe = pathlib.Path(sumo.SUMO_HOME) / "bin" / "netconvert"
        if exe.exists():
            return str(exe)
    except ImportError:
        pass
    found = shutil.which("netconvert")
    if not found:
        raise BuildError("--sumo: netconvert not found; install the 'osm' extra (eclipse-sumo) of caviar-plugins")
    return found


def street_level(tags: dict[str, str]) -> bool:
    if tags.get("tunnel") in ("yes", "culvert") or tags.get("location") == "underground":
        return False
    if tags.get("indoor", "no") != "no" or tags.get("highway") == "corridor":
        return False
    try:
        if float(tags.get("layer", "0").split(";")[0]) < 0:
            return False
    except ValueError:
        pass
    level = tags.get("level")
    if level is not None:
        try:
            if any(float(v) != 0 for v in level.replace(",", ";").split(";") if v.strip()):
                return False
        except ValueError:
            pass
    return True


def road_ways(data: OsmData, bbox: BBox | None) -> list[Way]:
    """Street-level highway ways with at least one node inside the bbox (all, without one)."""
    out = []
    for w in data.highways:
        if not street_level(w.tags):
            continue
        ok = np.isfinite(w.lonlat).all(axis=1)
        if ok.sum() < 2:
            continue
        if bbox is None or bbox.contains(w.lonlat[ok, 0], w.lonlat[ok, 1]).any():
            out.append(w)
    return out


def write_osm_xml(data: OsmData, ways: list[Way], path: pathlib.Path) -> dict[int, tuple[float, float]]:
    """Copies the given ways and their nodes (with tags: signals, crossings) from the
    input into an OSM XML file netconvert reads. Returns node id → (lon, lat)."""
    import osmium

    keep_ways = {w.id for w in ways}
    keep_nodes = {int(r) for w in ways for r in w.refs}
    coords = {}
    if path.exists():
        path.unlink()
    writer = osmium.SimpleWriter(str(path))

    class Copy(osmium.SimpleHandler):
        def node(self, n):
            if n.id in keep_nodes:
                writer.add_node(n)
                coords[n.id] = (n.location.lon, n.location.lat)

        def way(self, w):
            if w.id in keep_ways:
                writer.add_way(w)

    try:
        Copy().apply_file(str(data.path))
    finally:
        writer.close()
    return coords


def build_network(data: OsmData, bbox: BBox | None, frame: Frame, out: pathlib.Path, log) -> dict:
    ways = road_ways(data, bbox)
    if not ways:
        raise BuildError(f"{data.path}: --sumo: no roads (highway ways) in the bbox")
    osm_xml = out / "roads.osm"
    coords = write_osm_xml(data, ways, osm_xml)
    log(f"  {len(ways)} highway ways, {len(coords)} nodes -> {osm_xml.name}; netconvert ...")
    net = out / "net.net.xml"
    cmd = [netconvert_binary(), "--osm-files", str(osm_xml), "-o", str(net), "--proj", frame.proj,
           "--offset.disable-normalization", "true", *NETCONVERT_OPTIONS]
    p = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    if p.returncode != 0 or not net.exists():
        last = (p.stderr.strip().splitlines() or ["no message"])[-1]
        raise BuildError(f"{data.path}: netconvert failed ({last})")
    warnings = sum(1 for line in p.stderr.splitlines() if line.startswith("Warning"))
    check = check_frame(net, coords, frame)
    if check["junctions_checked"] and check["max_error_m"] > 0.1:
        raise BuildError(f"{net}: the network is not in the scene frame (junctions up to "
                         f"{check['max_error_m']:.2f} m from their OSM nodes)")
    info = network_summary(net)
    info.update(check, file=net.name, osm_xml=osm_xml.name, netconvert_warnings=warnings,
                netconvert_options=["--proj", frame.proj, "--offset.disable-normalization", "true",
                                    *NETCONVERT_OPTIONS])
    return info


def junctions(net: pathlib.Path) -> list[dict]:
    """Non-internal junctions: id, type, x, y."""
    out = []
    for _, el in ET.iterparse(net):
        if el.tag == "junction" and el.get("type") != "internal":
            out.append({"id": el.get("id"), "type": el.get("type"),
                        "x": float(el.get("x", "nan")), "y": float(el.get("y", "nan"))})
        el.clear() if el.tag in ("edge", "junction", "connection") else None
    return out


def network_summary(net: pathlib.Path) -> dict:
    edges = lanes = crossings = walking = 0
    location = {}
    for _, el in ET.iterparse(net):
        if el.tag == "location":
            location = dict(el.attrib)
        elif el.tag == "edge":
            fn = el.get("function")
            if fn == "crossing":
                crossings += 1
            elif fn == "walkingarea":
                walking += 1
            elif fn != "internal":
                edges += 1
                lanes += sum(1 for c in el if c.tag == "lane")
            el.clear()
    return {"edges": edges, "lanes": lanes, "crossings": crossings, "walkingareas": walking,
            "junctions": len(junctions(net)), "location": location}


def check_frame(net: pathlib.Path, coords: dict[int, tuple[float, float]], frame: Frame) -> dict:
    js = [j for j in junctions(net) if j["id"].isdigit() and int(j["id"]) in coords]
    if not js:
        return {"junctions_checked": 0, "max_error_m": float("nan")}
    ll = np.array([coords[int(j["id"])] for j in js])
    x, y = frame.to_xy(ll[:, 0], ll[:, 1])
    err = np.hypot(np.array([j["x"] for j in js]) - x, np.array([j["y"] for j in js]) - y)
    return {"junctions_checked": len(js), "max_error_m": round(float(err.max()), 4)}
