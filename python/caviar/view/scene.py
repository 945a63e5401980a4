"""The run's 3D scene for the page: the Mitsuba XML its config names, the PLY meshes
that XML references (the only files outside the run directory the server hands out),
and the transmitter's position."""

from __future__ import annotations

import math
import pathlib
import xml.etree.ElementTree as ET

from caviar.view.contract import CORE, ViewContract


def _modules(config: dict) -> list[tuple[str, dict]]:
    mods = config.get("modules") if isinstance(config, dict) else None
    return [(k, v) for k, v in mods.items() if isinstance(v, dict)] if isinstance(mods, dict) else []


def find_scene(config: dict, config_dir: pathlib.Path | None, run_dir: pathlib.Path,
               contract: ViewContract = CORE) -> tuple[str, pathlib.Path | None, str]:
    """(name, XML path or None, where the name came from): a module's ``scene``
    parameter, else the plugins' default scene; a bare name is looked up in the
    plugins' scene folders (both from their view contract)."""
    name, origin = contract.default_scene, "default (no module sets a 'scene' parameter)"
    for mod, spec in _modules(config):
        params = spec.get("params")
        if isinstance(params, dict) and isinstance(params.get("scene"), str):
            name, origin = params["scene"], f"modules.{mod}.params.scene"
            break
    if name.endswith(".xml") or "/" in name:
        for base in [b for b in (config_dir, run_dir) if b is not None]:
            p = (base / name)
            if p.is_file():
                return name, p.resolve(), origin
        return name, None, origin
    for d in contract.scene_dirs:
        p = pathlib.Path(d) / name / f"{name}.xml"
        if p.is_file():
            return name, p.resolve(), origin
    return name, None, origin


def _transform(shape: ET.Element) -> list[float] | None:
    """The shape's ``to_world`` as a row-major 4×4 matrix (translate, scale, rotate,
    matrix; each later element applied after the earlier ones, as in Mitsuba)."""
    import numpy as np

    tr = next((t for t in shape.findall("transform") if t.get("name") == "to_world"), None)
    if tr is None:
        return None
    m = np.eye(4)

    def vec(el: ET.Element, default: float) -> list[float]:
        value = el.get("value")
        if value is not None:
            v = [float(x) for x in value.replace(",", " ").split()]
            return v * 3 if len(v) == 1 else v
        return [float(el.get(k, default)) for k in "xyz"]

    for el in tr:
        a = np.eye(4)
        if el.tag == "translate":
            a[:3, 3] = vec(el, 0.0)
        elif el.tag == "scale":
            a[0, 0], a[1, 1], a[2, 2] = vec(el, 1.0)
        elif el.tag == "rotate":
            axis = np.array(vec(el, 0.0), dtype=float)
            n = np.linalg.norm(axis)
            if n == 0:
                continue
            x, y, z = axis / n
            th = math.radians(float(el.get("angle", 0)))
            c, s, C = math.cos(th), math.sin(th), 1 - math.cos(th)
            a[:3, :3] = [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                         [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                         [z * x * C - y * s, z * y * C + x * s, c + z * z * C]]
        elif el.tag == "matrix":
            # No value: an empty matrix, which reshape refuses (a bad scene, reported as such).
            a = np.array([float(v) for v in el.get("value", "").split()]).reshape(4, 4)
        else:
            continue
        m = a @ m
    return [round(float(v), 6) for v in m.reshape(-1)]


def scene_meshes(xml: pathlib.Path) -> list[dict]:
    """The PLY shapes of a Mitsuba scene: id, file (resolved), material, to_world."""
    root = ET.parse(xml).getroot()
    out = []
    for shape in root.iter("shape"):
        if shape.get("type") != "ply":
            continue
        fn = next((s.get("value") for s in shape.findall("string") if s.get("name") == "filename"), None)
        if not fn:
            continue
        path = (xml.parent / fn).resolve()
        if not path.is_file():
            continue
        ref = next((r.get("id") for r in shape.findall("ref") if r.get("name") in ("bsdf", None)), None)
        out.append({"id": shape.get("id") or path.stem, "file": path, "material": ref or "",
                    "matrix": _transform(shape)})
    return out


def transmitter(config: dict, contract: ViewContract = CORE) -> dict | None:
    """The Tx position a module's parameters give (``tx_position``), else the default of
    its plugin (the plugins' view contract), else None."""
    for mod, spec in _modules(config):
        params = spec.get("params")
        tx = params.get("tx_position") if isinstance(params, dict) else None
        if isinstance(tx, list) and len(tx) == 3:
            try:
                return {"position": [float(v) for v in tx], "origin": f"modules.{mod}.params.tx_position"}
            except (TypeError, ValueError):
                pass
    defaults = dict(contract.default_transmitters)
    for mod, spec in _modules(config):
        if spec.get("plugin") in defaults:
            return {"position": list(defaults[spec["plugin"]]),
                    "origin": f"default of plugin {spec['plugin']} (modules.{mod})"}
    return None
