"""Mitsuba 3 scene files as Sionna RT 2.x loads them: ``itu-radio-material`` BSDFs and
binary PLY meshes (``face_normals``: flat shading, as radio needs)."""

from __future__ import annotations

import pathlib
from xml.sax.saxutils import quoteattr

import numpy as np

from caviar_plugins.osm.extrude import Mesh
from caviar_plugins.osm.materials import THICKNESS_M


def write_ply(path: pathlib.Path, mesh: Mesh) -> None:
    """Binary little-endian PLY: float32 x, y, z; uchar-counted int32 triangles."""
    v = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    f = np.zeros(len(mesh.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    f["n"] = 3
    f["i"] = mesh.faces
    header = ("ply\nformat binary_little_endian 1.0\ncomment CAVIAR scene from OpenStreetMap\n"
              f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(v.tobytes())
        out.write(f.tobytes())


def read_ply(path: pathlib.Path) -> Mesh:
    """Reads back what :func:`write_ply` writes."""
    data = pathlib.Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").split("\n")
    nv = int(next(line for line in head if line.startswith("element vertex")).split()[-1])
    nf = int(next(line for line in head if line.startswith("element face")).split()[-1])
    v = np.frombuffer(data, dtype="<f4", count=nv * 3, offset=end).reshape(nv, 3)
    f = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=end + nv * 12)
    return Mesh(v.astype(float), f["i"].astype(np.int64))


def scene_xml(shapes: list[tuple[str, str, str]], comment: str) -> str:
    """shapes: (shape id, PLY path relative to the XML, ITU material type)."""
    materials = sorted({m for _, _, m in shapes})
    lines = [f"<!--\n{comment}\n-->", '<scene version="2.1.0">']
    for m in materials:
        lines += [f'\t<bsdf type="itu-radio-material" id="mat-itu_{m}">',
                  f'\t\t<string name="type" value="{m}"/>',
                  f'\t\t<float name="thickness" value="{THICKNESS_M}"/>',
                  "\t</bsdf>"]
    lines.append("")
    for sid, ply, m in shapes:
        lines += [f"\t<shape type=\"ply\" id={quoteattr(sid)}>",
                  f"\t\t<string name=\"filename\" value={quoteattr(ply)}/>",
                  '\t\t<boolean name="face_normals" value="true"/>',
                  f'\t\t<ref id="mat-itu_{m}" name="bsdf"/>',
                  "\t</shape>"]
    lines.append("</scene>\n")
    return "\n".join(lines)


def scene_shapes(xml_path) -> list[tuple[str, pathlib.Path, str]]:
    """(shape id, absolute PLY path, ITU material type) of the PLY shapes of a scene
    file written here (or any Mitsuba XML of that form): lets a renderer that builds its
    own Mitsuba scene (the camera plugin) use the meshes of ``scene = "DIR/scene.xml"``."""
    import xml.etree.ElementTree as ET

    xml_path = pathlib.Path(xml_path)
    root = ET.parse(xml_path).getroot()
    types = {b.get("id"): next((s.get("value") for s in b.iter("string") if s.get("name") == "type"), "")
             for b in root.iter("bsdf")}
    out = []
    for shape in root.iter("shape"):
        if shape.get("type") != "ply":
            continue
        fname = next((s.get("value") for s in shape.iter("string") if s.get("name") == "filename"), None)
        ref = next((r.get("id") for r in shape.iter("ref")), None)
        if fname:
            sid = shape.get("id") or pathlib.Path(fname).stem
            out.append((sid, (xml_path.parent / fname).resolve(), types.get(ref or "", "") or ""))
    return out
