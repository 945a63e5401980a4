"""Reading an OSM extract (XML or PBF) offline with pyosmium: building ways and
relations, and (for road surfaces and SUMO) highway ways.

What counts as a building: a way or a ``type=multipolygon`` relation with a
``building`` tag other than ``no``. Inside a bbox means every node of it (for a
relation, of all its member ways) lies inside: buildings cut by the bbox are left out,
not clipped. Ways (and relations) whose nodes are missing from the extract count as
outside.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from caviar_plugins.osm import BuildError
from caviar_plugins.osm.frame import BBox

ROAD_WIDTH_M = {  # carriageway width by highway type, where no width/lanes tag says
    "motorway": 14.0, "trunk": 12.0, "primary": 10.0, "secondary": 9.0, "tertiary": 8.0, "unclassified": 6.0,
    "residential": 6.0, "living_street": 5.0, "service": 4.0, "pedestrian": 5.0, "motorway_link": 6.0,
    "trunk_link": 6.0, "primary_link": 6.0, "secondary_link": 6.0, "tertiary_link": 6.0, "road": 6.0,
}


@dataclasses.dataclass
class Way:
    id: int
    tags: dict[str, str]
    refs: np.ndarray
    """Node ids."""
    lonlat: np.ndarray
    """(N, 2) degrees; NaN where the node is missing from the extract."""

    @property
    def complete(self) -> bool:
        return bool(np.isfinite(self.lonlat).all())

    @property
    def closed(self) -> bool:
        return len(self.refs) >= 4 and self.refs[0] == self.refs[-1]

    def inside(self, bbox: BBox | None) -> bool:
        if not self.complete:
            return False
        return bbox is None or bool(bbox.contains(self.lonlat[:, 0], self.lonlat[:, 1]).all())


@dataclasses.dataclass
class Relation:
    id: int
    tags: dict[str, str]
    members: list[tuple[str, int]]
    """(role, way id) of the member ways."""
    ways: list[tuple[str, Way]] = dataclasses.field(default_factory=list)

    def inside(self, bbox: BBox | None) -> bool:
        return (len(self.ways) == len(self.members) and len(self.ways) > 0
                and all(w.inside(bbox) for _, w in self.ways))


@dataclasses.dataclass
class OsmData:
    path: pathlib.Path
    building_ways: list[Way]
    building_relations: list[Relation]
    highways: list[Way]
    bounds: BBox | None
    """Of the file's header, where it has one."""


def is_building(tags) -> bool:
    v = tags.get("building")
    return v is not None and v != "no"


def _check_input(path: pathlib.Path) -> None:
    if not path.exists():
        raise BuildError(f"{path}: no such file")
    if not path.is_file():
        raise BuildError(f"{path}: not a file")
    name = path.name.lower()
    if not name.endswith((".osm", ".pbf", ".osm.bz2", ".osm.gz")):
        raise BuildError(f"{path}: unknown format; expected .osm (XML) or .osm.pbf")


def _way(w) -> Way:
    """A way with its node ids and (lon, lat) (NaN where a location is missing)."""
    n = len(w.nodes)
    refs = np.empty(n, dtype=np.int64)
    ll = np.full((n, 2), np.nan)
    for i, nd in enumerate(w.nodes):
        refs[i] = nd.ref
        if nd.location.valid():
            ll[i] = nd.location.lon, nd.location.lat
    return Way(w.id, {t.k: t.v for t in w.tags}, refs, ll)


def _building_relations(path: pathlib.Path) -> dict[int, Relation]:
    """Pass 1: multipolygon relations tagged building."""
    import osmium

    relations: dict[int, Relation] = {}

    class Rel(osmium.SimpleHandler):
        def relation(self, r):
            if r.tags.get("type") == "multipolygon" and is_building(r.tags):
                members = [(m.role or "outer", m.ref) for m in r.members if m.type == "w"]
                relations[r.id] = Relation(r.id, {t.k: t.v for t in r.tags}, members)

    Rel().apply_file(str(path))
    return relations


def _ways(path: pathlib.Path, roads: bool, wanted: set[int]) -> tuple[list[Way], list[Way], dict[int, Way]]:
    """Pass 2: building ways, highways (if ``roads``) and the ways in ``wanted``, with locations."""
    import osmium

    ways: list[Way] = []
    highways: list[Way] = []
    members: dict[int, Way] = {}

    class Ways(osmium.SimpleHandler):
        def way(self, w):
            b = is_building(w.tags)
            h = roads and "highway" in w.tags
            m = w.id in wanted
            if not (b or h or m):
                return
            way = _way(w)
            if b:
                ways.append(way)
            if h:
                highways.append(way)
            if m:
                members[w.id] = way

    Ways().apply_file(str(path), locations=True)
    return ways, highways, members


def _file_bounds(path: pathlib.Path) -> BBox | None:
    """The bounding box in the file's header, where it has a valid one."""
    import osmium

    header = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
    box = header.header().box()
    header.close()
    if not box.valid():
        return None
    bl, tr = box.bottom_left, box.top_right
    try:
        return BBox(bl.lat, bl.lon, tr.lat, tr.lon).checked()
    except ValueError:
        return None


def read(path: pathlib.Path, roads: bool = True) -> OsmData:
    """Two passes: relations first (to know which ways are members of building
    multipolygons), then ways with node locations."""
    path = pathlib.Path(path)
    _check_input(path)
    try:
        relations = _building_relations(path)
        wanted = {ref for r in relations.values() for _, ref in r.members}
        ways, highways, members = _ways(path, roads, wanted)
        bounds = _file_bounds(path)
    except (RuntimeError, ValueError, OSError) as e:
        msg = " ".join(str(e).split()) or type(e).__name__
        raise BuildError(f"{path}: not a readable OSM file ({msg})") from None
    for r in relations.values():
        r.ways = [(role, members[ref]) for role, ref in r.members if ref in members]
    return OsmData(path, ways, list(relations.values()), highways, bounds)


def road_width(tags: dict[str, str]) -> float | None:
    """Carriageway width in metres: ``width``, else ``lanes`` × 3.25 m, else by type;
    None for ways that are not roads for vehicles (paths, steps, ...)."""
    kind = tags.get("highway", "")
    if kind not in ROAD_WIDTH_M:
        return None
    w = parse_length(tags.get("width"))
    if w and 1 <= w <= 60:
        return w
    try:
        lanes = int(tags.get("lanes", ""))
        if 1 <= lanes <= 12:
            return lanes * 3.25
    except ValueError:
        pass
    return ROAD_WIDTH_M[kind]


def parse_length(text: str | None) -> float | None:
    """'12', '12 m', '12.5m', "40'" (feet), '3,5' → metres; None if unreadable."""
    if not text:
        return None
    t = text.strip().lower().replace(",", ".")
    factor = 1.0
    if t.endswith("'") or t.endswith("ft"):
        factor, t = 0.3048, t.rstrip("'").removesuffix("ft")
    t = t.removesuffix("m").strip()
    try:
        v = float(t) * factor
    except ValueError:
        return None
    return v if np.isfinite(v) and v > 0 else None
