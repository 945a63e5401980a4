"""Standard deployments from a few keys: the hexagonal layout of TR 38.901 §7.8 and its
UE drops.

``layout = { kind = "hex", rings = 2, isd_m = 500, sectors = 3, height_m = 25,
wraparound = true, ues_per_sector = 10 }`` gives 19 sites × 3 sectors (sector boresights
30°, 150°, 270°) and drops 10 UEs in every sector as TR 38.901 Table 7.8-1 says: uniform
over the sector's part of its site's hexagon, at least ``min_distance_m`` from the site
(2D, indoor distance included), indoor with probability ``indoor_share`` on floor
``n ~ U{1..N}``, ``N ~ U{4..8}`` (height ``3(n − 1) + 1.5`` m; TR 36.873), outdoor at 1.5 m.

Sionna SYS ships the sites, the drop and the indoor distances
(:func:`sionna.sys.gen_tr38901_multicell_topology`); this module turns them into the network's
cells and UEs and redoes none of them. With ``wraparound``, each UE sees every site at the
image nearest to it (of the site and its 6 copies around the layout, :class:`Wraparound`:
the translations that tile the plane, computed here), so a UE at the layout's edge has
interferers all around it, as one in the middle does.
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


def site_positions(layout: LayoutSettings) -> np.ndarray:
    """The sites' (x, y) in metres, [num_sites, 2], in Sionna's order (centre first). (Sionna
    drops a UE per sector on the way: under a seed of its own, Sionna's random state put back.)"""
    from sionna.sys import gen_tr38901_multicell_topology

    from caviar_plugins.rt.sionna_adapter import seeded

    with seeded(0):
        _, xy = gen_tr38901_multicell_topology(
            "uma", batch_size=1, num_ut_per_sector=1, carrier_frequency=6e9, num_rings=layout.rings,
            use_3gpp_calibration_defaults=False, isd=float(layout.isd_m), bs_height=float(layout.height_m),
            min_bs_ut_dist=0.0, indoor_probability=0.0, return_site_positions=True)
    return xy.detach().cpu().double().numpy() + np.array(layout.center_m)


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
            indoor_probability=float(layout.indoor_share))
    ut_loc, in_state, d_in = topo[0], topo[5], topo[10]
    d_in = d_in.detach().cpu().double().numpy()[0]
    if d_in.ndim == 2:  # link-specific below 6 GHz ([cell, ut]): the home site's value
        home = np.arange(d_in.shape[1]) // layout.ues_per_sector
        d_in = d_in[home, np.arange(d_in.shape[1])]
    positions = ut_loc.detach().cpu().double().numpy()[0]
    positions[:, :2] += np.array(layout.center_m)
    return Drop(positions=positions,
                indoor=in_state.detach().cpu().numpy()[0].astype(bool), distance_2d_in=d_in)
