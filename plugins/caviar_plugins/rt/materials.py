"""A scene's radio materials as numbers: what they are at the scene's carrier
(:func:`scene_materials`), changing them (:func:`apply_materials`), a material of its own for
a group of objects (:func:`split_material`), and a scene file with learned materials (:func:`write_scene_xml`,
each named :func:`fitted_name`).

The properties are Sionna RT's (ITU-R P.2040): the real relative permittivity
``relative_permittivity`` (ε_r ≥ 1), the conductivity ``conductivity`` (σ, S/m), the
``scattering_coefficient`` (S in [0, 1], the share of the reflected field that is
scattered diffusely) and the ``thickness`` (m). An ITU material's ε_r and σ follow the
carrier (ε_r = a·f^b, σ = c·f^d with f in GHz); :func:`fix_at_carrier` freezes them at the
scene's carrier, which is what a fit learns and what :func:`write_scene_xml` writes.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import os
import pathlib
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from typing import Any

from caviar_plugins.rt.scene import sionna_rt

PROPERTIES = ("relative_permittivity", "conductivity", "scattering_coefficient")
"""What a material fit can learn, as Sionna names them."""


@dataclasses.dataclass(frozen=True)
class MaterialValues:
    """One radio material at one carrier."""

    relative_permittivity: float
    conductivity: float
    scattering_coefficient: float = 0.0
    thickness: float = 0.1

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def _scalar(value: Any) -> float:
    return float(value[0]) if hasattr(value, "__len__") else float(value)


def material_of(scene: Any, name: str) -> Any:
    """The scene's radio material ``name``, or a KeyError naming the ones it has."""
    try:
        return scene.radio_materials[name]
    except KeyError:
        raise KeyError(f"material '{name}': the scene has {', '.join(sorted(used_materials(scene)))}") from None


def used_materials(scene: Any) -> list[str]:
    """The materials at least one object of ``scene`` uses, sorted."""
    return sorted({obj.radio_material.name for obj in scene.objects.values()})


def scene_materials(scene: Any) -> dict[str, MaterialValues]:
    """Every used material's values at the scene's carrier."""
    out = {}
    for name in used_materials(scene):
        m = scene.radio_materials[name]
        out[name] = MaterialValues(_scalar(m.relative_permittivity), _scalar(m.conductivity),
                                   _scalar(m.scattering_coefficient), _scalar(m.thickness))
    return out


def fix_at_carrier(scene: Any) -> None:
    """Keeps every material's ε_r and σ at their values for the scene's carrier: a later
    change of carrier no longer recomputes them (so that set values stay)."""
    for m in scene.radio_materials.values():
        if hasattr(m, "frequency_update_callback"):
            m.frequency_update_callback = None


def apply_materials(scene: Any, values: Mapping[str, Mapping[str, float]]) -> None:
    """Sets ``{material: {property: value}}`` on ``scene`` (properties of
    :data:`PROPERTIES` and ``thickness``), after :func:`fix_at_carrier`. Unknown materials
    or properties: a KeyError naming them."""
    fix_at_carrier(scene)
    for name, props in values.items():
        m = material_of(scene, name)
        for prop, v in props.items():
            if prop not in (*PROPERTIES, "thickness"):
                raise KeyError(f"material '{name}': unknown property '{prop}' (expected one of "
                               f"{', '.join((*PROPERTIES, 'thickness'))})")
            setattr(m, prop, float(v))


def split_material(scene: Any, group: str, patterns: Iterable[str]) -> list[str]:
    """Gives the objects whose names match ``patterns`` (shell globs) a material of their
    own, named ``group``, a copy of the one they had at the scene's carrier (all matched
    objects must share one material). The scene must be loaded with its shapes unmerged.
    Returns the objects' names; a ValueError when none matches or their materials differ."""
    patterns = list(patterns)
    objs = [o for name, o in sorted(scene.objects.items())
            if any(fnmatch.fnmatchcase(name, p) for p in patterns)]
    if not objs:
        raise ValueError(f"group '{group}': no object of the scene matches {patterns} "
                         f"(objects: {', '.join(sorted(scene.objects)[:8])}…)")
    bases = {o.radio_material.name for o in objs}
    if len(bases) > 1:
        raise ValueError(f"group '{group}': its objects have different materials ({', '.join(sorted(bases))}); "
                         "a group must share one")
    base = scene_materials(scene)[bases.pop()]
    mat = sionna_rt().RadioMaterial(group, **base.as_dict())
    for o in objs:
        o.radio_material = mat
    return [o.name for o in objs]


def fitted_name(name: str) -> str:
    """The name a learned material has in a written scene: ``fitted-`` and its name without
    ``itu_`` (Sionna reads every material named ``itu_…``, or named like an ITU material, as
    that ITU material, whatever its values)."""
    base = name[4:] if name.startswith(("itu_", "itu-")) else name
    return f"fitted-{base}"


def write_scene_xml(source: pathlib.Path, target: pathlib.Path, values: Mapping[str, MaterialValues],
                    groups: Mapping[str, list[str]] | None = None) -> dict[str, str]:
    """Writes ``source`` (a Mitsuba/Sionna XML scene) to ``target`` with every material of
    ``values`` a plain ``radio-material`` of those values, named :func:`fitted_name`, and the
    shapes of each group of ``groups`` (``{group: [shape names]}``) on a material of their own.
    Mesh paths are made relative to ``target``'s folder, so the new file loads from where it
    is. Returns ``{material: its name in the new file}``."""
    source, target = pathlib.Path(source), pathlib.Path(target)
    tree = ET.parse(source)
    root = tree.getroot()
    by_name = {_material_name(b): b for b in root.iter("bsdf")}
    for name in groups or {}:
        if name in by_name:
            raise ValueError(f"group '{name}': the scene already has a material of that name")
        by_name[name] = ET.Element("bsdf", {"type": "radio-material", "id": name})
        root.insert(0, by_name[name])
    _move_shapes(root, groups or {}, source)
    renamed = {}
    for name, v in values.items():
        if name not in by_name:
            raise KeyError(f"material '{name}': not in {source}")
        renamed[name] = _write_material(root, by_name[name], fitted_name(name), v)
    for node in root.iter("string"):
        if node.get("name") == "filename":
            mesh = (source.parent / node.get("value", "")).resolve()
            node.set("value", os.path.relpath(mesh, target.parent.resolve()))
    target.parent.mkdir(parents=True, exist_ok=True)
    ET.indent(tree)
    tree.write(target, encoding="unicode")
    return renamed


def _material_name(bsdf: ET.Element) -> str:
    """Sionna's name of a material: its XML id without ``mat-``."""
    bsdf_id = bsdf.get("id", "")
    return bsdf_id[4:] if bsdf_id.startswith("mat-") else bsdf_id


def _write_material(root: ET.Element, bsdf: ET.Element, name: str, v: MaterialValues) -> str:
    """Makes ``bsdf`` a plain radio material ``name`` of values ``v`` (the shapes' references
    follow); returns ``name``."""
    old = bsdf.get("id", "")
    for ref in root.iter("ref"):
        if ref.get("id") == old:
            ref.set("id", name)
    bsdf.attrib["id"] = name
    bsdf.attrib["type"] = "radio-material"
    for child in list(bsdf):
        bsdf.remove(child)
    for prop, value in v.as_dict().items():
        ET.SubElement(bsdf, "float", {"name": prop, "value": repr(float(value))})
    return name


def _move_shapes(root: ET.Element, groups: Mapping[str, list[str]], source: pathlib.Path) -> None:
    """Points each group's shapes at the group's material."""
    shapes = {s.get("id", ""): s for s in root.iter("shape")}
    for name, members in groups.items():
        for member in members:
            shape = shapes.get(member) or shapes.get(f"mesh-{member}")
            if shape is None:
                raise KeyError(f"group '{name}': shape '{member}' not in {source}")
            for ref in shape.iter("ref"):
                if ref.get("name") == "bsdf":
                    ref.set("id", name)
