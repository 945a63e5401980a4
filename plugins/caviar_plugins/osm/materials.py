"""ITU-R P.2040 radio materials (Sionna RT's ``itu-radio-material`` types) from OSM tags.

A building's material comes from, in order, ``building:facade:material``,
``building:material``, ``facade:material``, ``building:cladding`` and, for glass
buildings, ``building=glasshouse|greenhouse``; values are mapped below. Anything else is
concrete. The ground and road surfaces are concrete too (P.2040's ground types are
defined only up to 10 GHz and asphalt is not among its materials).

Validity (Sionna RT 2.x): concrete 1-100 GHz, glass 0.1-100 GHz, metal 1-100 GHz,
wood 0.001-100 GHz, brick 1-40 GHz (a brick scene above 40 GHz fails to load; use
``--no-brick`` then, which maps brick to concrete).
"""

from __future__ import annotations

TAGS = ("building:facade:material", "building:material", "facade:material", "building:cladding")

VALUES = {
    "glass": "glass", "mirror": "glass", "glass_facade": "glass",
    "metal": "metal", "steel": "metal", "aluminium": "metal", "aluminum": "metal", "copper": "metal",
    "metal_plates": "metal", "sheet_metal": "metal", "tin": "metal", "zinc": "metal",
    "brick": "brick", "bricks": "brick", "clinker": "brick",
    "wood": "wood", "timber_framing": "wood", "timber": "wood", "log": "wood", "wooden": "wood",
    "concrete": "concrete", "stone": "concrete", "plaster": "concrete", "cement_block": "concrete",
    "sandstone": "concrete", "limestone": "concrete", "masonry": "concrete", "granite": "concrete",
}

MATERIALS = ("concrete", "brick", "glass", "metal", "wood")
THICKNESS_M = 0.1


def building_material(tags: dict[str, str], brick: bool = True) -> str:
    for key in TAGS:
        value = tags.get(key, "").strip().lower()
        if value:
            m = VALUES.get(value.split(";")[0].strip())
            if m:
                return "concrete" if (m == "brick" and not brick) else m
    if tags.get("building") in ("glasshouse", "greenhouse"):
        return "glass"
    return "concrete"
