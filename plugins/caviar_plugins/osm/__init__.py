"""A ray-tracing scene and a road network from any OpenStreetMap extract, without Blender.

    caviar-core scene build INPUT.osm|INPUT.osm.pbf --out DIR [--bbox S,W,N,E | --center LAT,LON --radius M]
                            [--decimate R] [--default-height M] [--roads] [--sumo]

(or ``python -m caviar_plugins.tools.scene build ...``). The pipeline (:mod:`.build`) reads the
file offline (:mod:`.reader`, pyosmium: OSM XML and PBF), projects it to a local
east-north-up frame in metres (:mod:`.frame`), extrudes building footprints
(:mod:`.extrude`), assigns ITU radio materials by tag (:mod:`.materials`), writes a
Mitsuba 3 scene that Sionna RT 2.x loads as it is (:mod:`.mitsuba`) and, with ``--sumo``,
a SUMO network in the same frame (:mod:`.sumo`).
"""


class BuildError(Exception):
    """Bad input or a failed step: the command line prints the message (one line, naming
    the file) and exits with status 2."""
