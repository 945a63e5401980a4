"""Standard deployments from a few keys: the hexagonal layout of TR 38.901 §7.8 and its
UE drops.

``layout = { kind = "hex", rings = 2, isd_m = 500, sectors = 3, height_m = 25,
wraparound = true, ues_per_sector = 10 }`` gives 19 sites × 3 sectors (sector boresights
30°, 150°, 270°) and drops 10 UEs in every sector as TR 38.901 Table 7.8-1 says: uniform
over the sector's cell, at least ``min_distance_m`` from the site (2D, indoor distance
included), indoor with probability ``indoor_share`` on floor ``n ~ U{1..N}``, ``N ~ U{4..8}``
(height ``3(n − 1) + 1.5`` m; TR 36.873), outdoor at 1.5 m.

The layout is 3GPP's (TR 36.814 Figure A.2.1.1-2, ITU-R M.2412's): the sites stand on a
hexagonal lattice with neighbours at 30°, 90°, … 330°, so each sector's boresight points at a
neighbouring site, and a sector's cell is a hexagon of radius ISD/3 centred ISD/3 from its
site along the boresight (the "clover leaf": the three cells of a site meet at it).

Sionna SYS ships the sites, the drop and the indoor distances
(:func:`sionna.sys.gen_tr38901_multicell_topology`); this module turns them into the network's
cells and UEs. Sionna's lattice has its neighbours at 0°, 60°, …, so its boresights point at
the corners of each site's hexagon and each sector's UEs fill a third of it (a rhombus around
the boresight): the layout and the drop are turned here by :data:`LATTICE_TURN_DEG`, and each
UE moved from that rhombus to the same place in its sector's cell (:func:`to_cells`: a
translation by the lattice and a turn by 120° about its site, which keeps the drop uniform, the
UE's distance from a site within ``min_distance_m`` excluded, and its floor and indoor distance).

With ``wraparound``, each UE sees every site at the image nearest to it (of the site and its
6 copies around the layout, :class:`Wraparound`: the translations that tile the plane, computed
here), so a UE at the layout's edge has interferers all around it, as one in the middle does.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

import caviar
from caviar_plugins.network.cells import Cell, Column, parse_sites

KINDS = ("hex",)
SECTOR_AZIMUTHS_DEG = (30.0, 150.0, 270.0)  # TR 38.901 Table 7.8 (and Sionna's topology)
LATTICE_TURN_DEG = 30.0
"""How far the layout is turned from Sionna's (whose neighbouring sites stand at 0°, 60°, …): to
3GPP's, where each boresight of :data:`SECTOR_AZIMUTHS_DEG` points at a neighbouring site
(Sionna's point at its hexagon's corners, and the wideband SIR came out 0.4–0.8 dB low)."""
DROP_SCENARIOS = ("uma", "umi", "rma")
REDROP = ("never", "every-step")


@dataclasses.dataclass(frozen=True)
class LayoutSettings:
    """A hexagonal multi-site layout and, optionally, its UE drop."""

    kind: str = "hex"
    rings: int = 2
    """Rings of sites around the centre one: 0 (1 site), 1 (7) or 2 (19)."""
    isd_m: float = 500.0
    """Inter-site distance (UMa 500 m, UMi 200 m, RMa 1732 m)."""
    sectors: int = 3
    height_m: float = 25.0
    """Antenna height of every site (UMa 25 m, UMi 10 m, RMa 35 m)."""
    wraparound: bool = True
    ues_per_sector: int = 0
    """UEs the network drops in every sector itself (TR 38.901 §7.8), beside the UEs that
    publish positions; 0: none."""
    indoor_share: float = 0.8
    min_distance_m: float = 35.0
    """Minimum 2D distance of a dropped UE from its site (UMa and RMa 35 m, UMi 10 m)."""
    scenario: str | None = None
    """Whose indoor-distance and height rules the drop follows (``uma``, ``umi``, ``rma``):
    the 38.901 channel's by default, else ``uma``."""
    redrop: str = "never"
    """``every-step``: a fresh drop at every step (the calibration's drops), each UE new;
    ``never``: one drop at setup, the UEs stay."""
    center_m: tuple[float, float] = (0.0, 0.0)
    """Where the centre site stands (x, y in the scene frame, metres): places the layout
    in a ray-traced scene."""

    def __post_init__(self):
        object.__setattr__(self, "given", caviar.given_keys())  # (which keys the configuration wrote)
        if self.kind not in KINDS:
            raise ValueError(f"kind: expected one of {list(KINDS)}, got {self.kind!r}")
        if self.rings not in (0, 1, 2) or isinstance(self.rings, bool):
            raise ValueError(f"rings: Sionna's 38.901 layout has 0, 1 or 2 rings (1, 7 or 19 sites), "
                             f"got {self.rings!r}")
        if self.sectors != 3:
            raise ValueError(f"sectors: the 38.901 hexagonal layout has 3 sectors per site (boresights "
                             f"30°, 150°, 270°), got {self.sectors!r}")
        for key in ("isd_m", "height_m"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key}: expected a positive number of metres, got {v!r}")
        if isinstance(self.ues_per_sector, bool) or not isinstance(self.ues_per_sector, int) \
                or self.ues_per_sector < 0:
            raise ValueError(f"ues_per_sector: expected a whole number >= 0, got {self.ues_per_sector!r}")
        if not 0.0 <= self.indoor_share <= 1.0:
            raise ValueError(f"indoor_share: expected a share in [0, 1], got {self.indoor_share!r}")
        if not 0.0 <= self.min_distance_m < self.isd_m / math.sqrt(3):
            raise ValueError(f"min_distance_m: expected metres in [0, {self.isd_m / math.sqrt(3):.1f}) "
                             f"(the cell radius isd_m/√3), got {self.min_distance_m!r}")
        if self.scenario is not None and self.scenario not in DROP_SCENARIOS:
            raise ValueError(f"scenario: expected one of {list(DROP_SCENARIOS)}, got {self.scenario!r}")
        center = self.center_m
        if not (isinstance(center, (list, tuple)) and len(center) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                        for v in center)):
            raise ValueError(f"center_m: expected [x, y] in metres, got {center!r}")
        object.__setattr__(self, "center_m", (float(center[0]), float(center[1])))
        if self.redrop not in REDROP:
            raise ValueError(f"redrop: expected one of {list(REDROP)}, got {self.redrop!r}")

    @property
    def num_sites(self) -> int:
        return 1 + 3 * self.rings * (self.rings + 1)


def _turn(xy: np.ndarray, deg: float = LATTICE_TURN_DEG) -> np.ndarray:
    """Points [..., 2] turned by ``deg`` about the origin."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def site_positions(layout: LayoutSettings) -> np.ndarray:
    """The sites' (x, y) in metres, [num_sites, 2], in Sionna's order (centre first), turned
    by :data:`LATTICE_TURN_DEG` to 3GPP's orientation. (Sionna drops a UE per sector on the
    way: under a seed of its own, Sionna's random state put back.)"""
    from sionna.sys import gen_tr38901_multicell_topology

    from caviar_plugins.rt.sionna_adapter import seeded

    with seeded(0):
        _, xy = gen_tr38901_multicell_topology(
            "uma", batch_size=1, num_ut_per_sector=1, carrier_frequency=6e9, num_rings=layout.rings,
            use_3gpp_calibration_defaults=False, isd=float(layout.isd_m), bs_height=float(layout.height_m),
            min_bs_ut_dist=0.0, indoor_probability=0.0, return_site_positions=True)
    return _turn(xy.detach().cpu().double().numpy()) + np.array(layout.center_m)


def to_cells(points: np.ndarray, sites: np.ndarray, isd: float, ues_per_sector: int) -> np.ndarray:
    """UEs [n, 2] dropped by Sionna (turned to the 3GPP lattice ``sites`` [site, 2], about the
    layout's centre at the origin), UE ``k`` in sector ``k // ues_per_sector`` (site-major, 3 a
    site), each moved to the same place in its sector's cell: the hexagon of radius ISD/3
    centred ISD/3 from its site along the sector's boresight.

    Sionna's sector, turned with the layout, is a third of its site's hexagon (a rhombus
    centred 30° past the boresight); its sides are vectors of the cells' lattice (√3·ISD/3 long,
    at 0°, 60°, …), so it and the cell hold the same points up to the cells' lattice. Moved by the vector of the sites'
    lattice that puts it in one of its own site's three cells, and turned by 120° about the site
    into its sector's cell, each point of the third lands on one point of the cell, the same
    area about (uniform stays uniform); within ISD/3 of the site nothing moves but by the turn,
    so the disk ``min_distance_m`` keeps out of the drop stays out of it."""
    r = isd / 3.0
    sector = np.arange(len(points)) // ues_per_sector
    site, j = sector // 3, sector % 3
    rel = points - sites[site]
    bores = np.radians(SECTOR_AZIMUTHS_DEG)
    centres = r * np.stack([np.cos(bores), np.sin(bores)], -1)  # [3, 2]: a site's cells
    turns = np.radians(LATTICE_TURN_DEG + 60.0 * np.arange(6))
    near = np.concatenate([np.zeros((1, 2)), isd * np.stack([np.cos(turns), np.sin(turns)], -1)])  # [7, 2]
    cand = near[:, None, :] + centres[None]  # [7 sites, 3 cells, 2]
    d = np.linalg.norm(rel[:, None, None, :] - cand[None], axis=-1).reshape(len(points), -1)
    best = d.argmin(axis=1)
    v, m = near[best // 3], best % 3
    a = np.radians(120.0 * (j - m))
    x, y = (rel - v).T
    return sites[site] + np.stack([np.cos(a) * x - np.sin(a) * y, np.sin(a) * x + np.cos(a) * y], axis=-1)


def layout_cells(layout: LayoutSettings, defaults: Mapping[str, Any], column: Column | None) -> list[Cell]:
    """The cells of the layout: site ``S<i>``, sectors ``S<i>/0..2``, with the network-wide
    power, carrier, bandwidth and array, and ``column`` behind each port."""
    sites = [{"name": f"S{i}", "position": [float(x), float(y), float(layout.height_m)],
              "azimuths_deg": list(SECTOR_AZIMUTHS_DEG)}
             for i, (x, y) in enumerate(site_positions(layout))]
    cells = parse_sites(sites, defaults)
    return [dataclasses.replace(c, column=column) for c in cells]


class Wraparound:
    """Where each UE sees each site: the nearest of the site's 7 images (the site and its
    6 copies around the layout).

    The copies are the layout moved by the 6 translations that tile the plane with it: for
    ``rings`` = R, the site lattice's vector (R + 1)·a₁ + R·a₂ and its turns by 60° (a₁ from
    the centre site to the first, a₂ that turned by 60°; √7·ISD for R = 1, √19·ISD for
    R = 2). Every point then sees its own site nearest, as in an endless layout. (Sionna
    2.2's ``gen_tr38901_multicell_topology`` returns images, ``bs_virtual_loc``, made with
    translations 30° off its own sites, which do not tile: 7 % of a 2-ring drop's UEs see
    a copy of another site nearer than their own, and the UMa calibration's median coupling
    loss came out 1.1 dB low.)"""

    def __init__(self, layout: LayoutSettings):
        sites = site_positions(layout)
        shifts = np.zeros((1, 2))  # (one site, rings = 0: nothing to wrap)
        if layout.rings > 0:
            a1 = sites[1] - sites[0]
            turn = np.radians(60.0 * np.arange(6))
            rot = np.stack([np.stack([np.cos(turn), -np.sin(turn)], -1),
                            np.stack([np.sin(turn), np.cos(turn)], -1)], -2)  # [6, 2, 2]
            a2 = rot[1] @ a1
            shift = (layout.rings + 1) * a1 + layout.rings * a2
            shifts = np.concatenate([np.zeros((1, 2)), rot @ shift], axis=0)  # [7, 2]
        self.shifts = shifts
        self.images = sites[:, None, :] + shifts[None]  # [site, 7, 2], in the cells' order

    def site_xy(self, ues: np.ndarray) -> np.ndarray:
        """[n_ue, n_site, 2]: the image of every site nearest to every UE (2D)."""
        d = np.linalg.norm(ues[:, None, None, :2] - self.images[None], axis=-1)  # [ue, site, 7]
        best = np.argmin(d, axis=-1)
        return np.take_along_axis(self.images[None], best[..., None, None], axis=2)[:, :, 0, :]


@dataclasses.dataclass
class Drop:
    """Dropped UEs: positions [n, 3], indoor [n], indoor 2D distance [n] (0 outdoors)."""

    positions: np.ndarray
    indoor: np.ndarray
    distance_2d_in: np.ndarray


MAX_REDROPS = 50
"""Fresh drops a ray-traced layout tries for a UE that fell under a roof."""


def drop_outdoors(layout: LayoutSettings, scenario: str, carrier_hz: float, seed: int,
                  outdoors: Any = None, sectors: Any = ()) -> Drop:
    """One drop (:func:`drop_ues`) drawn from ``seed``; with ``outdoors`` (whether points
    [n, 3] stand under open sky: a scene's), a UE dropped under a roof is dropped again in
    its sector (``sectors``: their names, for the error) until it is outdoors, uniform over
    the sector's open ground, at most :data:`MAX_REDROPS` times."""
    drop = drop_ues(layout, scenario, carrier_hz, seed)
    if outdoors is None:
        return drop
    inside = ~outdoors(drop.positions)
    for again in range(1, MAX_REDROPS + 1):
        if not inside.any():
            break
        more = drop_ues(layout, scenario, carrier_hz, seed + 7_919 * again).positions  # (the same sectors, k by k)
        drop.positions[inside] = more[inside]
        inside[inside] = ~outdoors(more[inside])
    if inside.any():
        names = sorted({sectors[k // layout.ues_per_sector] for k in np.flatnonzero(inside)})
        raise caviar.ConfigError(f"{MAX_REDROPS} drops found no open ground in sector(s) {', '.join(names)}: move "
                                 f"the layout with layout.center_m", "params.layout.center_m")
    return drop


def drop_ues(layout: LayoutSettings, scenario: str, carrier_hz: float, seed: int) -> Drop:
    """One drop of ``ues_per_sector`` UEs in every sector, drawn by Sionna from ``seed``
    (its random state put back afterwards: :func:`~caviar_plugins.rt.sionna_adapter.seeded`).
    UE ``k`` is in sector ``k // ues_per_sector`` (site-major)."""
    from sionna.sys import gen_tr38901_multicell_topology

    from caviar_plugins.rt.sionna_adapter import seeded

    with seeded(seed):
        topo = gen_tr38901_multicell_topology(
            scenario, batch_size=1, num_ut_per_sector=layout.ues_per_sector, carrier_frequency=float(carrier_hz),
            num_rings=layout.rings, use_3gpp_calibration_defaults=False, isd=float(layout.isd_m),
            bs_height=float(layout.height_m), min_bs_ut_dist=float(layout.min_distance_m),
            indoor_probability=float(layout.indoor_share), return_site_positions=True)
    topo, site_xy = topo
    ut_loc, in_state, d_in = topo[0], topo[5], topo[10]
    d_in = d_in.detach().cpu().double().numpy()[0]
    if d_in.ndim == 2:  # link-specific below 6 GHz ([cell, ut]): the home site's value
        home = np.arange(d_in.shape[1]) // layout.ues_per_sector
        d_in = d_in[home, np.arange(d_in.shape[1])]
    positions = ut_loc.detach().cpu().double().numpy()[0]
    sites = _turn(site_xy.detach().cpu().double().numpy())  # (site_positions' without the centre)
    positions[:, :2] = to_cells(_turn(positions[:, :2]), sites, float(layout.isd_m), layout.ues_per_sector)
    positions[:, :2] += np.array(layout.center_m)
    return Drop(positions=positions,
                indoor=in_state.detach().cpu().numpy()[0].astype(bool), distance_2d_in=d_in)
