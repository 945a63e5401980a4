"""A radio network of many cells: sites and sectors, RSRP and SINR with interference,
A3 handover and radio-link failure, and the link level of Sionna SYS (proportional-fair
scheduling, outer-loop link adaptation, PHY abstraction on NR BLER tables).

The plugin is ``radio-network`` (:mod:`caviar_plugins.network.plugin`); its pieces are
plain modules usable alone: :mod:`~caviar_plugins.network.cells`,
:mod:`~caviar_plugins.network.handover`, :mod:`~caviar_plugins.radio.link_level`.
"""
