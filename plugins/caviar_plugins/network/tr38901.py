"""The TR 38.901 stochastic channel (UMa, UMi, RMa) of the radio network: pathloss, LOS
probability, shadow fading and O2I penetration from Sionna's models
(:mod:`sionna.phy.channel.tr38901`, PyTorch), the antenna patterns from the network's
cells (:func:`~caviar_plugins.network.cells.pattern_gain_db`), no fast fading.

Large-scale parameters belong to a **site**, not a sector (TR 38.901 §7.5: co-sited
sectors share them): Sionna draws them per site, and each sector adds its pattern toward
the UE, seen from the site's image nearest to the UE when the layout wraps around.

A UE keeps its LOS state, shadow fading and (indoors) O2I loss while it moves less than
``redraw_m`` from where they were drawn (a piecewise-constant stand-in for the spatial consistency of
§7.6.3: the decorrelation distances of Table 7.5-6 are 37–120 m); the pathloss follows
its position at every step. A UE that has not moved keeps its gains as they were.

Indoor UEs (the drop's) get the O2I loss of a low-loss or a high-loss building (Table
7.4.3-2), ``o2i_high_loss_share`` of them the high-loss one.

``spec_version`` chooses the release of TR 38.901 whose tables Sionna uses
(:data:`SPEC_VERSIONS`). For this channel (pathloss, LOS probability, shadow fading, O2I;
no fast fading) the two differ only in the high-loss building's IRR glass.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from caviar_plugins.network.cells import Cell, pattern_gain_db
from caviar_plugins.network.layout import Wraparound
from caviar_plugins.torch_device import resolve

CHANNELS = {"38.901-uma": "uma", "38.901-umi": "umi", "38.901-rma": "rma"}
# TR 38.901 Table 7.4.1-1: where the pathloss models hold (carrier frequency).
VALID_CARRIER_HZ = {"uma": (0.5e9, 100e9), "umi": (0.5e9, 100e9), "rma": (0.5e9, 30e9)}
# Table 7.4.1-1: UE heights the models take (a higher UE, an aerial one, is clipped for the
# pathloss only; TR 36.777's aerial models are not part of this channel).
UE_HEIGHT_M = {"uma": (1.5, 22.5), "umi": (1.5, 22.5), "rma": (1.0, 10.0)}
# Decorrelation distance of the shadow fading in NLOS (Table 7.5-6).
REDRAW_M = {"uma": 50.0, "umi": 13.0, "rma": 120.0}
SPEC_VERSIONS = {
    "16.1": "TR 38.901 V16.1.0 (2019-12): the O2I high-loss IRR glass of 23 + 0.3·f dB (f in GHz), as in "
            "TR 38.900 V14.0.0 (2016-06), with which the 3GPP phase-1 calibration (R1-165974) was made",
    "19.2": "TR 38.901 V19.2.0 (Release 19): IRR glass of 25.4 + 0.11·f dB (the glass loses 1.3 dB more at "
            "6 GHz, 3.3 dB less at 30 GHz, 10.9 dB less at 70 GHz), and Release 19's delay and angle spreads "
            "(unused here)",
}
"""The releases of TR 38.901 Sionna's scenarios implement (their ``spec_version``), and what
each means for this channel."""


@dataclasses.dataclass(frozen=True)
class StochasticSettings:
    """Settings of the TR 38.901 channel (``params.tr38901``)."""

    o2i_high_loss_share: float = 0.5
    """Share of indoor UEs in high-loss buildings (TR 38.901 Table 7.8-1: 50 %)."""
    shadow_fading: bool = True
    redraw_m: float | None = None
    """How far a UE moves before its LOS state and shadow fading are drawn again; the
    scenario's NLOS shadow-fading decorrelation distance by default (UMa 50 m, UMi 13 m,
    RMa 120 m)."""
    spec_version: str = "19.2"
    """The release of TR 38.901's tables (:data:`SPEC_VERSIONS`): ``19.2`` (Sionna's default,
    the latest) or ``16.1`` (the O2I model of the 2016 calibration)."""

    def __post_init__(self):
        if self.spec_version not in SPEC_VERSIONS:
            raise ValueError(f"spec_version: expected one of {list(SPEC_VERSIONS)} (the releases of TR 38.901 "
                             f"Sionna implements), got {self.spec_version!r}")
        if not 0.0 <= self.o2i_high_loss_share <= 1.0:
            raise ValueError(f"o2i_high_loss_share: expected a share in [0, 1], got {self.o2i_high_loss_share!r}")
        if self.redraw_m is not None and not self.redraw_m > 0:
            raise ValueError(f"redraw_m: expected a positive distance in metres, got {self.redraw_m!r}")


def check_carrier(scenario: str, carrier_hz: float, key: str) -> None:
    lo, hi = VALID_CARRIER_HZ[scenario]
    if not lo <= carrier_hz <= hi:
        raise ValueError(f"{key}: TR 38.901's {scenario.upper()} model holds from {lo / 1e9:g} to "
                         f"{hi / 1e9:g} GHz, got {carrier_hz / 1e9:g} GHz")


@dataclasses.dataclass
class _Draw:
    """What a UE keeps between steps: where its state was drawn, its LOS state and shadow
    fading per site, its building and O2I loss, and the gains it last had (and where).

    ``los`` is the outdoor part's LOS state (Sionna's ``outdoor_los``), which chooses the
    pathloss formula for an indoor UE too (TR 38.901 §7.4.3: PL_b of the outdoor distance);
    Sionna's ``los`` is False for every indoor UE (an O2I link has no LOS component)."""

    anchor: np.ndarray
    los: np.ndarray  # [site] bool: the outdoor part's
    sf_db: np.ndarray  # [site]
    indoor: bool
    distance_2d_in: float
    high_loss: bool
    position: np.ndarray
    site_gain_db: np.ndarray  # [site]: −pathloss − shadow fading
    o2i_db: np.ndarray | None = None  # [site]: the O2I loss drawn with it (0 outdoors; None: a checkpoint
    # written before it was kept, whose moves draw it again)


class StochasticChannel:
    """Large-scale channel gains of every cell toward every UE, for one scenario."""

    def __init__(self, scenario: str, cells: list[Cell], settings: StochasticSettings,
                 wraparound: Wraparound | None = None, device: str | None = None, seed: int = 0):
        """``wraparound``: each UE sees each site at its nearest image (None: the sites
        themselves). ``device``: the torch device of Sionna's models (default: Sionna's)."""
        import torch
        from sionna.phy.channel.tr38901 import LSPGenerator, PanelArray, RMaScenario, UMaScenario, UMiScenario

        self.scenario = scenario
        self.cells = cells
        self.settings = settings
        self.device = str(resolve("auto") if device is None else resolve(device))
        self.wraparound = wraparound
        self.sites = list(dict.fromkeys(c.site for c in cells))
        self.cell_site = np.array([self.sites.index(c.site) for c in cells])
        first = [next(c for c in cells if c.site == s) for s in self.sites]
        self.site_position = np.array([c.position for c in first])  # [site, 3]
        self.site_height = self.site_position[:, 2]
        self.redraw_m = settings.redraw_m or REDRAW_M[scenario]
        carrier = cells[0].carrier_hz
        model = {"uma": UMaScenario, "umi": UMiScenario, "rma": RMaScenario}[scenario]
        # One omnidirectional element at both ends: the cells' own patterns are applied here.
        array = PanelArray(num_rows_per_panel=1, num_cols_per_panel=1, polarization="single",
                           polarization_type="V", antenna_pattern="omni", carrier_frequency=carrier,
                           precision="double", device=self.device)
        kw = dict(carrier_frequency=carrier, ut_array=array, bs_array=array, direction="downlink",
                  enable_shadow_fading=settings.shadow_fading, precision="double", device=self.device,
                  spec_version=settings.spec_version)
        self.models = {loss: model(o2i_model=loss, **kw) for loss in ("low", "high")}
        self.lsp = {loss: LSPGenerator(m) for loss, m in self.models.items()}
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.torch = torch
        self.state: dict[str, _Draw] = {}
        self.calls = 0  # gains_db calls: each seeds Sionna's random state anew (resumable)

    def snapshot(self) -> dict:
        """What a checkpoint keeps: every UE's draw, the call count and the building draws."""
        return {"ues": self.state, "calls": self.calls, "rng": self.rng.bit_generator.state}

    def restore(self, saved: dict) -> None:
        self.state, self.calls = saved["ues"], saved["calls"]
        self.rng.bit_generator.state = saved["rng"]

    # -- Sionna ------------------------------------------------------------------------
    def _sample(self, loss: str, pos: np.ndarray, site_xy: np.ndarray, indoor: np.ndarray,
                d_in: np.ndarray, los: np.ndarray | None):
        """Pathloss (dB), its O2I part (dB) and shadow fading (dB) per [ue, site] from Sionna's
        model, and the outdoor LOS state, with ``los`` [ue, site] forced (None: drawn)."""
        torch = self.torch
        model = self.models[loss]
        n_ue, n_site = len(pos), len(self.sites)
        lo, hi = UE_HEIGHT_M[self.scenario]
        ut = pos.copy()
        ut[:, 2] = np.clip(ut[:, 2], lo, hi)

        def t(a, dtype=torch.float64):
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=self.device)

        bs = np.concatenate([site_xy, np.broadcast_to(self.site_height[None, :, None], (n_ue, n_site, 1))],
                            axis=-1)  # [ue, site, 3]
        model.reset_topology()
        kwargs = {}
        if self.scenario == "rma":
            kwargs["in_car"] = t(np.zeros((1, n_ue)), torch.bool)
        model.set_topology(
            ut_loc=t(ut[None]), bs_loc=t(bs[:1]), ut_orientations=t(np.zeros((1, n_ue, 3))),
            bs_orientations=t(np.zeros((1, n_site, 3))), ut_velocities=t(np.zeros((1, n_ue, 3))),
            in_state=t(indoor[None], torch.bool),
            los="random" if los is None else t(los.T[None], torch.bool),
            bs_virtual_loc=t(bs.transpose(1, 0, 2)[None]), bs_site_ids=t(np.arange(n_site), torch.int64),
            distance_2d_in=t(d_in[None]), **kwargs)
        self.lsp[loss].reset_topology()
        self.lsp[loss].topology_updated_callback()  # (what SystemLevelChannel.set_topology does)
        lsp = self.lsp[loss]()
        pl = lsp.pathloss.detach().cpu().double().numpy()[0].T  # [ue, site]
        o2i = pl - model.basic_pathloss.detach().cpu().double().numpy()[0].T
        sf = 10 * np.log10(lsp.sf.detach().cpu().double().numpy()[0].T)
        if not self.settings.shadow_fading:
            sf = np.zeros_like(sf)
        drawn = model.outdoor_los.detach().cpu().numpy()[0].T if los is None else los
        return pl, o2i, sf, drawn.astype(bool)

    # -- the network's side -------------------------------------------------------------
    def forget(self, ue: str) -> None:
        self.state.pop(ue, None)

    def gains_db(self, ids: list[str], pos: np.ndarray, indoor: np.ndarray | None = None,
                 distance_2d_in: np.ndarray | None = None) -> np.ndarray:
        """Channel gains (dB: −pathloss − shadow fading + the cell's pattern) of every
        cell toward the UEs ``ids`` at ``pos`` [n, 3]: [n_ue, n_cell]. ``indoor`` and
        ``distance_2d_in`` describe UEs seen for the first time (default: outdoor). Each call
        draws from a seed of its own (the run's and the call count: resumable), with Sionna's
        random state put back afterwards (:func:`~caviar_plugins.rt.sionna_adapter.seeded`)."""
        from caviar_plugins.rt.sionna_adapter import seeded

        self.calls += 1
        with seeded(self.seed * 1_000_003 + 7919 * (self.calls - 1) + 1):
            return self._gains_db(ids, pos, indoor, distance_2d_in)

    def _gains_db(self, ids: list[str], pos: np.ndarray, indoor: np.ndarray | None,
                  distance_2d_in: np.ndarray | None) -> np.ndarray:
        n = len(ids)
        indoor = np.zeros(n, bool) if indoor is None else np.asarray(indoor, bool)
        d_in = np.zeros(n) if distance_2d_in is None else np.asarray(distance_2d_in, float)
        site_xy = (self.wraparound.site_xy(pos) if self.wraparound is not None  # [ue, site, 2]
                   else np.broadcast_to(self.site_position[None, :, :2], (n, len(self.sites), 2)))
        fresh, moved = [], []
        for i, u in enumerate(ids):
            s = self.state.get(u)
            if s is None or np.linalg.norm(pos[i, :2] - s.anchor[:2]) > self.redraw_m:
                fresh.append(i)
            elif not np.array_equal(pos[i], s.position):
                moved.append(i)
        kept = {i: self._kept(ids[i], indoor[i], d_in[i]) for i in fresh + moved}
        for group, forced in ((fresh, False), (moved, True)):
            for loss in ("low", "high"):
                rows = [i for i in group if kept[i][0] == loss]
                if not rows:
                    continue
                r = np.array(rows)
                ind = np.array([kept[i][1] for i in rows])
                din = np.array([kept[i][2] for i in rows])
                los = np.array([self.state[ids[i]].los for i in rows]) if forced else None
                pl, o2i, sf, los_drawn = self._sample(loss, pos[r], site_xy[r], ind, din, los)
                for k, i in enumerate(rows):
                    if forced:  # the pathloss at the new position, the O2I loss kept (its random term)
                        s = self.state[ids[i]]
                        kept_o2i = o2i[k] if s.o2i_db is None else s.o2i_db
                        s.position, s.site_gain_db = pos[i].copy(), -(pl[k] - o2i[k] + kept_o2i) - s.sf_db
                    else:
                        self.state[ids[i]] = _Draw(anchor=pos[i].copy(), los=los_drawn[k], sf_db=sf[k],
                                                   indoor=bool(ind[k]), distance_2d_in=float(din[k]),
                                                   high_loss=loss == "high", position=pos[i].copy(),
                                                   site_gain_db=-pl[k] - sf[k], o2i_db=o2i[k])
        site_gain = np.array([self.state[u].site_gain_db for u in ids]).reshape(n, len(self.sites))
        return site_gain[:, self.cell_site] + self._patterns(pos, site_xy)

    def _kept(self, ue: str, indoor: bool, d_in: float) -> tuple[str, bool, float]:
        """A UE's building (``low``/``high`` loss), indoor state and indoor distance: those it
        was first drawn with, or for a new UE the given ones and a building drawn now."""
        s = self.state.get(ue)
        if s is not None:
            return ("high" if s.high_loss else "low"), s.indoor, s.distance_2d_in
        if not indoor:
            return "low", False, float(d_in)  # (outdoors the O2I model plays no part)
        return ("high" if self.rng.random() < self.settings.o2i_high_loss_share else "low"), True, float(d_in)

    def _patterns(self, pos: np.ndarray, site_xy: np.ndarray) -> np.ndarray:
        """Each cell's pattern (dBi) toward each UE, from the site image the UE sees."""
        out = np.empty((len(pos), len(self.cells)))
        for k, c in enumerate(self.cells):
            src = site_xy[:, self.cell_site[k]]
            d = pos[:, :2] - src
            phi = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
            theta = np.degrees(np.arctan2(np.hypot(d[:, 0], d[:, 1]), pos[:, 2] - c.position[2]))
            out[:, k] = pattern_gain_db(c, theta, phi)
        return out


class Tr38901Channel:
    """The ``38.901-*`` channels on the network's side: :class:`StochasticChannel`'s
    large-scale gains, flat in frequency, without path directions (no SSB beams)."""

    directions = False
    flat = True

    def __init__(self, kind: str, scenario: str, cells: list[Cell], settings: StochasticSettings,
                 wraparound: Wraparound | None = None, device: Any = None, seed: int = 0):
        self.kind = kind
        self.model = StochasticChannel(scenario, cells, settings, wraparound, device=device, seed=seed)

    def gains_db(self, t: float, ues: Any) -> np.ndarray:
        return self.model.gains_db(ues.ids, ues.positions, ues.indoor, ues.distance_2d_in)[..., None]

    def beam_gains(self, ues: Any, codebooks: Any) -> np.ndarray:
        raise ValueError(f"beams: the {self.kind} channel has no path directions")

    def forget(self, ue: str) -> None:
        self.model.forget(ue)

    def outdoors(self, points: np.ndarray) -> np.ndarray:
        return np.ones(len(points), dtype=bool)

    def state(self) -> dict:
        return self.model.snapshot()

    def restore(self, state: dict) -> None:
        self.model.restore(state)
