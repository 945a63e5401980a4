"""The pipeline of ``scene build``: named steps, each timed and reported on one line.

    read -> select -> extrude -> roads -> decimate -> write -> sumo

Output (DIR):
  scene.xml      Mitsuba 3 scene for Sionna RT 2.x (``scene = "DIR/scene.xml"``)
  meshes/*.ply   one merged mesh per material (``buildings-concrete.ply`` ...), ``ground.ply``
                 and, with --roads, ``roads.ply``
  scene.json     origin, PROJ string, bbox, counts, settings, step times
  net.net.xml    with --sumo: the SUMO network in the same frame (and roads.osm, its input)
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import platform
import time
from importlib import metadata

import numpy as np

from caviar_plugins.osm import BuildError
from caviar_plugins.osm.extrude import Mesh, decimate, flat_surface, footprint, height_of, prism, rectangle
from caviar_plugins.osm.frame import BBox, Frame
from caviar_plugins.osm.materials import building_material
from caviar_plugins.osm.mitsuba import scene_xml, write_ply
from caviar_plugins.osm.reader import read, road_width

ROAD_Z_M = 0.05
"""Road surfaces lie this far above the ground plane (no coplanar faces)."""


@dataclasses.dataclass
class Settings:
    input: pathlib.Path
    out: pathlib.Path
    bbox: BBox | None = None
    decimate: float = 1.0
    """Fraction of the faces kept (1 = no decimation); applied to each merged mesh."""
    default_height: float = 10.0
    roads: bool = False
    sumo: bool = False
    per_building: bool = False
    """One shape per building instead of one per material (for comparisons: slower ray tracing)."""
    brick: bool = True
    ground_margin: float = 0.0
    """Metres the ground plane extends beyond the bbox."""

    def __post_init__(self):
        if not 0 < self.decimate <= 1:
            raise BuildError(f"--decimate: expected a fraction of faces to keep in (0, 1], got {self.decimate}")
        if not self.default_height > 0:
            raise BuildError(f"--default-height: expected a positive number of metres, got {self.default_height}")


class Pipeline:
    def __init__(self, s: Settings, log=None):
        self.s = s
        self.log = log or (lambda msg: print(msg, flush=True))  # stdout; errors alone go to stderr
        self.times: dict[str, float] = {}
        self.info: dict = {}

    def step(self, name: str, fn):
        self.log(f"[{name}] ...")
        t0 = time.perf_counter()
        result = fn()
        self.times[name] = round(time.perf_counter() - t0, 3)
        self.log(f"[{name}] done in {self.times[name]:.2f} s")
        return result

    def run(self) -> dict:
        s = self.s
        t0 = time.perf_counter()
        self.data = self.step("read", lambda: read(s.input, roads=s.roads or s.sumo))
        self.step("select", self.select)
        self.step("extrude", self.extrude)
        if s.roads:
            self.step("roads", self.road_surfaces)
        self.step("decimate", self.decimate)
        self.step("write", self.write)
        if s.sumo:
            from caviar_plugins.osm.sumo import build_network

            self.info["sumo"] = self.step("sumo", lambda: build_network(self.data, self.bbox, self.frame, s.out,
                                                                         self.log))
        self.times["total"] = round(time.perf_counter() - t0, 3)
        self.info["step_seconds"] = self.times
        (s.out / "scene.json").write_text(json.dumps(self.info, indent=2) + "\n")
        self.log(f"scene: {s.out / 'scene.xml'} ({self.info['buildings']} buildings, "
                 f"{self.info['faces']['total']} faces) in {self.times['total']:.1f} s")
        return self.info

    # -- steps ---------------------------------------------------------------------

    def select(self):
        s, d = self.s, self.data
        bbox = s.bbox
        ways = [w for w in d.building_ways if w.inside(bbox)]
        rels = [r for r in d.building_relations if r.inside(bbox)]
        if not ways and not rels:
            where = f"in the bbox {','.join(f'{v:g}' for v in bbox.as_list())}" if bbox else "in the file"
            total = len(d.building_ways) + len(d.building_relations)
            raise BuildError(f"{s.input}: no buildings {where} ({total} in the whole file)")
        if bbox is None:
            ll = np.concatenate([w.lonlat for w in ways] + [w.lonlat for r in rels for _, w in r.ways])
            bbox = BBox(float(ll[:, 1].min()), float(ll[:, 0].min()), float(ll[:, 1].max()), float(ll[:, 0].max()))
        self.bbox_given = s.bbox is not None
        self.bbox = bbox if self.bbox_given else None
        lat, lon = bbox.centre
        self.frame = Frame(lat, lon)
        self.objects = ways + rels
        # The ground: the bbox's extent in the frame (its edges are slightly curved there).
        t = np.linspace(0, 1, 9)
        lons = np.concatenate([bbox.west + t * (bbox.east - bbox.west), np.full(9, bbox.east),
                               bbox.west + t * (bbox.east - bbox.west), np.full(9, bbox.west)])
        lats = np.concatenate([np.full(9, bbox.south), bbox.south + t * (bbox.north - bbox.south),
                               np.full(9, bbox.north), bbox.south + t * (bbox.north - bbox.south)])
        x, y = self.frame.to_xy(lons, lats)
        m = s.ground_margin + (0.0 if self.bbox_given else 20.0)
        self.extent = (float(x.min()) - m, float(y.min()) - m, float(x.max()) + m, float(y.max()) + m)
        self.info.update({
            "input": str(s.input), "frame": "x east, y north, z up, metres; ground at z = 0; origin at the "
            "bbox centre (transverse Mercator, scale 1 at the origin)",
            "origin": {"lat": lat, "lon": lon}, "proj": self.frame.proj,
            "bbox": {"south": bbox.south, "west": bbox.west, "north": bbox.north, "east": bbox.east,
                     "given": self.bbox_given},
            "extent_m": [round(v, 3) for v in self.extent],
        })
        self.log(f"  origin {lat:.6f}, {lon:.6f}; {len(ways)} building ways + {len(rels)} relations in the bbox "
                 f"({self.extent[2] - self.extent[0]:.0f} x {self.extent[3] - self.extent[1]:.0f} m)")

    def extrude(self):
        s = self.s
        self.buildings: list[tuple[str, str, Mesh]] = []  # (name, material, mesh)
        heights = {"height": 0, "levels": 0, "default": 0}
        skipped = []
        to_xy = self.frame.to_xy
        for k, obj in enumerate(self.objects):
            kind = "way" if hasattr(obj, "refs") else "relation"
            poly = footprint(obj, to_xy)
            if poly is None:
                skipped.append(f"{kind}/{obj.id}")
                continue
            h, src = height_of(obj.tags, s.default_height)
            heights[src] += 1
            self.buildings.append((f"{kind}{obj.id}", building_material(obj.tags, s.brick), prism(poly, h)))
            if (k + 1) % 2000 == 0:
                self.log(f"  {k + 1} / {len(self.objects)} buildings")
        if not self.buildings:
            raise BuildError(f"{s.input}: none of the {len(self.objects)} buildings in the bbox has a valid footprint")
        mats: dict[str, int] = {}
        for _, m, _ in self.buildings:
            mats[m] = mats.get(m, 0) + 1
        self.info.update({
            "buildings": len(self.buildings),
            "building_ways": sum(1 for o in self.objects if hasattr(o, "refs")),
            "building_relations": sum(1 for o in self.objects if not hasattr(o, "refs")),
            "skipped_no_footprint": skipped, "height_from": heights, "materials": mats,
        })

    def road_surfaces(self):
        from shapely.geometry import LineString, box
        from shapely.ops import unary_union

        lines = []
        for w in self.data.highways:
            width = road_width(w.tags)
            ok = np.isfinite(w.lonlat).all(axis=1)
            if width is None or ok.sum() < 2 or w.tags.get("area") == "yes":
                continue
            x, y = self.frame.to_xy(w.lonlat[ok, 0], w.lonlat[ok, 1])
            lines.append(LineString(np.column_stack([x, y])).buffer(width / 2, cap_style="flat", join_style="round",
                                                                    quad_segs=2))
        x0, y0, x1, y1 = self.extent
        area = unary_union(lines).intersection(box(x0, y0, x1, y1)) if lines else None
        self.roads = flat_surface(area, ROAD_Z_M) if area is not None and not area.is_empty else None
        self.info["roads"] = {"ways": len(lines), "area_m2": round(float(area.area), 1) if area is not None else 0.0,
                              "z_m": ROAD_Z_M}

    def decimate(self):
        s = self.s
        if s.per_building:
            groups = [(f"building-{name}", m, [mesh]) for name, m, mesh in self.buildings]
        else:
            by_mat: dict[str, list[Mesh]] = {}
            for _, m, mesh in self.buildings:
                by_mat.setdefault(m, []).append(mesh)
            groups = [(f"buildings-{m}", m, meshes) for m, meshes in sorted(by_mat.items())]
        self.shapes = []
        before = after = 0
        for name, m, meshes in groups:
            merged = Mesh.merge(meshes)
            out = decimate(merged, s.decimate)
            before += len(merged.faces)
            after += len(out.faces)
            if len(out.faces):
                self.shapes.append((name, m, out))
        self.info["building_faces_before_decimation"] = before
        if s.decimate < 1:
            self.log(f"  {before} -> {after} building faces (kept {after / before:.1%}, asked {s.decimate:.0%})")

    def write(self):
        s = self.s
        meshes_dir = s.out / "meshes"
        meshes_dir.mkdir(parents=True, exist_ok=True)
        for old in meshes_dir.glob("*.ply"):
            old.unlink()
        shapes = list(self.shapes) + [("ground", "concrete", rectangle(*self.extent))]
        if s.roads and self.roads is not None:
            shapes.append(("roads", "concrete", self.roads))
        entries = []
        faces = {}
        for name, m, mesh in shapes:
            write_ply(meshes_dir / f"{name}.ply", mesh)
            entries.append((name, f"meshes/{name}.ply", m))
            faces[name] = int(len(mesh.faces))
        faces["buildings"] = sum(v for k, v in faces.items() if k.startswith("building"))
        faces["total"] = sum(v for k, v in faces.items() if k != "buildings")
        self.info["faces"] = faces
        bbox = self.info["bbox"]
        comment = (f"  Built by `caviar-core scene build` from {s.input.name} (map data (c) OpenStreetMap "
                   "contributors, ODbL).\n"
                   f"  Frame: x east, y north, z up, metres; origin {self.info['origin']['lat']:.7f}, "
                   f"{self.info['origin']['lon']:.7f} on the ground (z = 0).\n"
                   f"  PROJ: {self.frame.proj}\n"
                   f"  BBox S,W,N,E: {bbox['south']:.7f},{bbox['west']:.7f},{bbox['north']:.7f},{bbox['east']:.7f}."
                   f" Buildings: {self.info['buildings']}. See scene.json.")
        (s.out / "scene.xml").write_text(scene_xml(entries, comment))
        self.info["settings"] = {
            "decimate_keep_fraction": s.decimate, "default_height_m": s.default_height, "roads": s.roads,
            "sumo": s.sumo, "per_building": s.per_building, "brick": s.brick,
        }
        self.info["versions"] = {"python": platform.python_version(), **_versions()}


def _versions() -> dict:
    out = {}
    for pkg in ("osmium", "pyproj", "shapely", "mapbox-earcut", "fast-simplification", "eclipse-sumo",
                "caviar-plugins"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def build(settings: Settings, log=None) -> dict:
    settings.out.mkdir(parents=True, exist_ok=True)
    return Pipeline(settings, log).run()
