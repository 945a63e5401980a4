"""Footprints (polygons with holes, in the scene frame) extruded to prisms.

Height: ``height`` (metres; "12 m", "40'" understood), else ``building:levels`` × 3 m
(plus ``roof:levels`` × 3 m), else the default. Buildings stand on the ground (z = 0);
``min_height`` is ignored. A prism's walls and flat roof share vertices (so decimation
sees one connected surface); it has no floor: the ground plane closes it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from caviar_plugins.osm.reader import Relation, Way, parse_length

LEVEL_M = 3.0


@dataclasses.dataclass
class Mesh:
    vertices: np.ndarray  # (V, 3) float
    faces: np.ndarray  # (F, 3) int

    @staticmethod
    def merge(meshes: list["Mesh"]) -> "Mesh":
        if not meshes:
            return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(np.concatenate([m.vertices for m in meshes]),
                    np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]))


def height_of(tags: dict[str, str], default: float) -> tuple[float, str]:
    """(height in metres, where it came from: 'height', 'levels' or 'default')."""
    h = parse_length(tags.get("height"))
    if h is not None and h < 1000:
        return h, "height"
    try:
        levels = float(tags.get("building:levels", "").replace(",", "."))
    except ValueError:
        levels = 0.0
    if 0 < levels < 300:
        try:
            roof = max(0.0, float(tags.get("roof:levels", "0").replace(",", ".")))
        except ValueError:
            roof = 0.0
        return (levels + roof) * LEVEL_M, "levels"
    return default, "default"


def footprint(obj: Way | Relation, to_xy):
    """A shapely (Multi)Polygon in the scene frame, or None when no area can be made."""
    import shapely
    from shapely.geometry import LineString, Polygon
    from shapely.ops import polygonize, unary_union

    def xy(way: Way) -> np.ndarray:
        x, y = to_xy(way.lonlat[:, 0], way.lonlat[:, 1])
        return np.column_stack([x, y])

    if isinstance(obj, Way):
        if not obj.closed:
            return None
        geom = Polygon(xy(obj))
    else:
        outer = [LineString(xy(w)) for role, w in obj.ways if role != "inner" and len(w.refs) >= 2]
        inner = [LineString(xy(w)) for role, w in obj.ways if role == "inner" and len(w.refs) >= 2]
        if not outer:
            return None
        geom = unary_union(list(polygonize(unary_union(outer))))
        if inner:
            geom = geom.difference(unary_union(list(polygonize(unary_union(inner)))))
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    polys = [g for g in getattr(geom, "geoms", [geom]) if g.geom_type == "Polygon" and g.area > 0.5]
    if not polys:
        return None
    return polys[0] if len(polys) == 1 else shapely.MultiPolygon(polys)


def prism(poly, height: float) -> Mesh:
    """Walls and a flat roof over a shapely Polygon or MultiPolygon (holes included);
    outward-facing triangles."""
    import mapbox_earcut as earcut
    from shapely.geometry.polygon import orient

    parts = []
    for p in getattr(poly, "geoms", [poly]):
        p = orient(p.simplify(0.05, preserve_topology=True), sign=1.0)  # outer CCW, holes CW
        rings = [np.asarray(p.exterior.coords)[:-1]] + [np.asarray(r.coords)[:-1] for r in p.interiors]
        rings = [r for r in rings if len(r) >= 3]
        if not rings:
            continue
        flat = np.concatenate(rings)
        n = len(flat)
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        roof = np.asarray(earcut.triangulate_float64(flat, ends), dtype=np.int64).reshape(-1, 3)
        # earcut's winding depends on the input: make every roof triangle face up.
        a, b, c = flat[roof[:, 0]], flat[roof[:, 1]], flat[roof[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        roof[cross < 0] = roof[cross < 0][:, ::-1]
        walls = []
        start = 0
        for r in rings:
            i = np.arange(start, start + len(r))
            j = np.roll(i, -1)
            # bottom vertices 0..n-1, top n..2n-1; (a0, b0, b1), (a0, b1, a1) face outward for a
            # CCW outer ring (and into the hole, away from the building, for a CW hole).
            walls.append(np.column_stack([i, j, j + n]))
            walls.append(np.column_stack([i, j + n, i + n]))
            start += len(r)
        v = np.concatenate([np.column_stack([flat, np.zeros(n)]), np.column_stack([flat, np.full(n, height)])])
        parts.append(Mesh(v, np.concatenate(walls + [roof + n])))
    return Mesh.merge(parts)


def rectangle(x0: float, y0: float, x1: float, y1: float, z: float = 0.0) -> Mesh:
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def flat_surface(geom, z: float) -> Mesh:
    """Triangulated upward-facing (Multi)Polygon at height z (road surfaces)."""
    import mapbox_earcut as earcut

    parts = []
    for p in getattr(geom, "geoms", [geom]):
        if p.geom_type != "Polygon" or p.area <= 0:
            continue
        rings = [np.asarray(p.exterior.coords)[:-1]] + [np.asarray(r.coords)[:-1] for r in p.interiors]
        rings = [r for r in rings if len(r) >= 3]
        flat = np.concatenate(rings)
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        tri = np.asarray(earcut.triangulate_float64(flat, ends), dtype=np.int64).reshape(-1, 3)
        a, b, c = flat[tri[:, 0]], flat[tri[:, 1]], flat[tri[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        tri[cross < 0] = tri[cross < 0][:, ::-1]
        parts.append(Mesh(np.column_stack([flat, np.full(len(flat), z)]), tri))
    return Mesh.merge(parts)


def decimate(mesh: Mesh, keep: float) -> Mesh:
    """Keeps about the fraction ``keep`` of the faces (quadric edge collapse,
    fast-simplification); keep = 1 returns the mesh unchanged."""
    if keep >= 1.0 or len(mesh.faces) == 0:
        return mesh
    import fast_simplification

    v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                        target_reduction=1.0 - keep)
    return Mesh(np.asarray(v, dtype=float), np.asarray(f, dtype=np.int64))
