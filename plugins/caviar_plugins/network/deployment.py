"""Where the radio network's cells are: a standard layout or hand-placed sites, and the NR
channel bandwidths in PRBs."""

from __future__ import annotations

import dataclasses
from typing import Any

from caviar_plugins.network.cells import Cell, parse_sites
from caviar_plugins.network.layout import layout_cells
from caviar_plugins.network.tr38901 import CHANNELS as STOCHASTIC
from caviar_plugins.network.tr38901 import check_carrier

# TS 38.101-1 Table 5.3.2-1 (FR1) and 38.101-2 Table 5.3.2-1 (FR2): PRBs per bandwidth (MHz).
NR_PRBS = {
    15e3: {5: 25, 10: 52, 15: 79, 20: 106, 25: 133, 30: 160, 40: 216, 50: 270},
    30e3: {5: 11, 10: 24, 15: 38, 20: 51, 25: 65, 30: 78, 40: 106, 50: 133, 60: 162, 70: 189, 80: 217,
           90: 245, 100: 273},
    60e3: {10: 11, 15: 18, 20: 24, 25: 31, 30: 38, 40: 51, 50: 65, 60: 79, 70: 93, 80: 107, 90: 121,
           100: 135, 200: 264},
    120e3: {50: 32, 100: 66, 200: 132, 400: 264},
}
def carrier_key(p: Any, cell: Cell) -> str:
    """The key that gave ``cell`` its carrier: ``carrier_hz`` or its site's ``sites.N.carrier_hz``."""
    if cell.carrier_hz == p.carrier_hz or p.layout is not None:
        return "carrier_hz"
    return f"sites.{[s.get('name') for s in p.sites].index(cell.site)}.carrier_hz"


def deployment(p: Any) -> list[Cell]:
    """The cells of the network's ``Params``: its standard ``layout`` or its hand-placed
    ``sites`` (not both), with the ``column`` behind each port; checked against the 38.901
    channel's carrier range."""
    if p.layout is not None and p.sites:
        given = getattr(p.layout, "given", None) or frozenset()
        if "wraparound" in given and p.layout.wraparound and "kind" not in given:
            raise ValueError("layout.wraparound: wraparound needs the hexagonal layout (layout.kind = \"hex\"); "
                             "hand-placed sites have no repeating pattern to wrap")
        raise ValueError("layout: conflicts with sites: give a standard layout or hand-placed "
                         "[[...params.sites]], not both")
    defaults = {k: getattr(p, k) for k in ("tx_power_dbm", "carrier_hz", "bandwidth_hz", "array")}
    if p.layout is not None:
        if p.channel == "ray-traced":
            if p.layout.wraparound:
                raise ValueError("layout.wraparound: a ray-traced scene is finite and does not repeat; set "
                                 "wraparound = false (the UEs at the layout's edge then see fewer interferers)")
            if p.layout.ues_per_sector and p.layout.indoor_share > 0:
                raise ValueError(f"layout.indoor_share: the ray tracer traces outdoor UEs only (no building "
                                 f"entry loss); set indoor_share = 0, got {p.layout.indoor_share!r}")
        cells = layout_cells(p.layout, defaults, p.column)
    else:
        cells = [dataclasses.replace(c, column=p.column) for c in parse_sites(p.sites, defaults)]
    if p.channel in STOCHASTIC:
        for c in cells:
            check_carrier(STOCHASTIC[p.channel], c.carrier_hz, carrier_key(p, c))
        if len({c.carrier_hz for c in cells}) > 1:
            raise ValueError(f"carrier_hz: the 38.901 channel models one carrier; the sites give "
                             f"{sorted({c.carrier_hz for c in cells})}")
    return cells


def nr_prbs(bandwidth_hz: float, scs_hz: float) -> int | None:
    table = NR_PRBS.get(scs_hz, {})
    mhz = bandwidth_hz / 1e6
    return table.get(int(mhz)) if float(mhz).is_integer() else None
