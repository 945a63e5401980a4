"""``caviar-core scene`` (and ``python -m caviar_plugins.tools.scene``): the command line of
:mod:`caviar_plugins.osm`, a Sionna RT scene and a SUMO network from OpenStreetMap."""
