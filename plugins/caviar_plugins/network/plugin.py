"""``radio-network``: a multi-cell radio network in the loop.

Every UE that publishes a position (UAVs, SUMO cars and pedestrians) measures every
cell; it attaches to the strongest, hands over on the A3 event, fails its radio link
when its SINR stays too low, and gets what the link level gives it (Sionna SYS:
proportional-fair scheduling, outer-loop link adaptation, PHY abstraction on NR BLER
tables; or Shannon). Publishes per step:

- ``communications.throughput`` (the paper's schema, Mbit/s of decoded bits) per UE;
- ``network.ue`` per UE: serving cell, RSRP of every cell, SINR, SIR, coupling loss, MCS,
  TBLER, HARQ (and, for a UE the layout dropped, its position);
- ``network.events``: attach, handover and radio-link-failure events;
- ``network.cells``: per cell, its UEs and the share of PRB-slots it used.

The channel (``channel``): free space (Friis with the 3GPP sector pattern) or ray-traced
(Sionna RT, every site in one solve, the sector patterns applied per path; refreshed every
``raytracing.refresh_s`` of virtual time). Between refreshes the ray-traced channel
evolves: as a UE moves, every path's phase turns by its displacement along the path's
direction of arrival (at the path's Doppler shift), evaluated at each step on
``subbands`` frequencies across the band, so the SINR fades in time and frequency and
the scheduler allocates per subband (``raytracing.evolve = "hold"`` freezes the paths'
power sum instead).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

import caviar
from caviar_plugins.network.beams import (
    BeamSettings,
    all_beam_gains,
    beam_report,
    beam_responses,
    gains_of_responses,
    line_of_sight,
    slot_beams,
    slot_sinr_db,
)
from caviar_plugins.network.cells import Cell, Column, line_of_sight_gain_db, noise_dbm, rsrp_dbm, rx_power_dbm, sinr_db
from caviar_plugins.network.deployment import carrier_key, deployment, nr_prbs
from caviar_plugins.network.handover import HandoverSettings, MobilityManager
from caviar_plugins.network.layout import LayoutSettings, Wraparound, drop_ues
from caviar_plugins.network.radio_map import RadioMapSettings, best_server_map, layer_message, save
from caviar_plugins.network.raytraced import SiteTracer, TracedChannels, TraceSettings, summed_db
from caviar_plugins.network.tr38901 import CHANNELS as STOCHASTIC
from caviar_plugins.network.tr38901 import StochasticChannel, StochasticSettings
from caviar_plugins.network.traffic import Queues, TrafficSettings, in_columns, transfer_record
from caviar_plugins.network.ues import UeTable, link_fields, ue_reports, uplink_fields
from caviar_plugins.network.uplink import UplinkSettings, uplink
from caviar_plugins.radio.link_level import LinkLevel, LinkSettings, check_nr_carrier
from caviar_plugins.schema import (
    ARRIVED,
    NETWORK_CELLS,
    NETWORK_EVENTS,
    NETWORK_RADIO_MAP,
    NETWORK_TRANSFERS,
    NETWORK_UE,
    POSITIONS,
    THROUGHPUT,
    VIEW_RADIO_MAP,
    ue_of,
)

INTERFERENCE = ("full-buffer", "scheduled")
CHANNELS = ("free-space", "ray-traced", *STOCHASTIC)
MAX_REDROPS = 50
"""Fresh drops a ray-traced layout tries for a UE that fell under a roof."""


class RadioNetwork(caviar.Plugin):
    subscribe = [POSITIONS, ARRIVED]
    optional = (ARRIVED,)  # (UEs that leave: SUMO's arrivals, when traffic runs)
    publishes = (THROUGHPUT, NETWORK_UE, NETWORK_EVENTS, NETWORK_CELLS, NETWORK_RADIO_MAP, VIEW_RADIO_MAP)

    @classmethod
    def inputs(cls, params):
        """The topics ``traffic.carry`` names: their messages go over the network."""
        if params.traffic is None:
            return {}
        return {c.topic: f"params.traffic.carry.{i}.topic" for i, c in enumerate(params.traffic.carry)}

    @classmethod
    def outputs(cls, params):
        """``network.transfers`` with a load, and where delivered messages go on."""
        if params.traffic is None:
            return ()
        return (NETWORK_TRANSFERS, *(f"{c.deliver_to}.*" for c in params.traffic.carry if c.deliver_to))

    @dataclasses.dataclass
    class Params:
        sites: list[dict] = dataclasses.field(default_factory=list)
        carrier_hz: float = 3.5e9
        bandwidth_hz: float = 20e6
        subcarrier_spacing_hz: float = 30e3
        num_prb: int | None = None
        tx_power_dbm: float = 43.0
        array: list[int] = dataclasses.field(default_factory=lambda: [4, 4])
        noise_figure_db: float = 7.0
        link_model: str = "sys"
        scheduler: str = "proportional-fair"
        interference: str = "full-buffer"
        bler_target: float = 0.1
        mcs_table: int = 1
        harq_processes: int = 1
        """Slots computed together, one per HARQ process (see
        :class:`~caviar_plugins.radio.link_level.LinkSettings`): 8 is about 5x faster."""
        compile: bool = False
        """``torch.compile`` the link level (Sionna SYS): about 4x faster a step, after
        about 20 s of compilation at the first step (see
        :class:`~caviar_plugins.radio.link_level.LinkSettings`)."""
        cuda_graphs: bool | None = None
        """With ``compile``, replay each compiled group of slots as a CUDA graph (None: on a
        CUDA device only; see :class:`~caviar_plugins.radio.link_level.LinkSettings`)."""
        device: str = "auto"
        """The torch device of the link level (Sionna SYS): ``auto`` (Sionna's choice, a GPU
        where there is one), ``cpu``, ``cuda`` or ``cuda:N``."""
        subbands: int = 8
        """Frequencies at which the ray-traced channel is evaluated, one per group of
        adjacent PRBs: the scheduler's unit and the EESM's inputs. The free-space channel
        is flat (one)."""
        handover: HandoverSettings = dataclasses.field(default_factory=HandoverSettings)
        """A3 handover and cell selection: ``offset_db``, ``hysteresis_db``,
        ``time_to_trigger_s``... (see :class:`~caviar_plugins.network.handover.HandoverSettings`)."""
        antenna_height_m: float = 1.5
        """A UE's antenna above the position it reports (SUMO reports the street)."""
        channel: str = "free-space"
        """``free-space`` (Friis along the straight line), ``ray-traced`` (Sionna RT, every
        site in one solve, refreshed every ``raytracing.refresh_s``) or TR 38.901's
        stochastic ``38.901-uma``, ``38.901-umi``, ``38.901-rma`` (Sionna's models: pathloss,
        LOS probability, shadow fading, O2I; no fast fading; see ``tr38901``)."""
        layout: LayoutSettings | None = None
        """A standard hexagonal deployment instead of hand-placed ``sites``: ``rings``,
        ``isd_m``, ``height_m``, ``wraparound``, and UEs dropped per sector
        (``ues_per_sector``...; see :class:`~caviar_plugins.network.layout.LayoutSettings`)."""
        column: Column | None = None
        """The elements behind each port: a vertical column with an electrical tilt (TR
        38.901 Table 7.8-1: ``{ elements = 10, spacing_wavelengths = 0.5,
        electrical_tilt_deg = 12 }``), part of every cell's pattern (see
        :class:`~caviar_plugins.network.cells.Column`)."""
        tr38901: StochasticSettings = dataclasses.field(default_factory=StochasticSettings)
        """The 38.901 channel's O2I building mix, shadow fading and redraw distance (see
        :class:`~caviar_plugins.network.tr38901.StochasticSettings`)."""
        report_cells: int = 0
        """``network.ue`` lists the RSRP of this many strongest cells (0: every cell), as a
        measurement report lists the serving cell and its best neighbours."""
        raytracing: TraceSettings = dataclasses.field(default_factory=TraceSettings)
        """``scene`` (default ``empty``), ``max_depth``, ``samples_per_src``, ``diffraction``,
        ``refresh_s``...: see :class:`~caviar_plugins.network.raytraced.TraceSettings`."""
        beams: BeamSettings | None = None
        """SSB beams from the channel (a table turns them on): every cell sweeps a DFT
        codebook of ``horizontal × vertical`` beams on its panel, L1-RSRP is the best beam's,
        data goes on the serving cell's best beam, and in each slot every other cell
        interferes with its beam toward the UE it schedules then, on the victim's channel
        (:mod:`~caviar_plugins.network.beams`). Needs the free-space or ray-traced channel."""
        uplink: UplinkSettings | None = None
        """The uplink (a table turns it on): PUSCH with open-loop power control (``p0_dbm``,
        ``alpha``, ``ue_max_power_dbm``), interference from the UEs other cells schedule in the
        slot, Sionna SYS on the PUSCH tables (:mod:`~caviar_plugins.network.uplink`);
        ``network.ue`` adds ``ul_*``."""
        traffic: TrafficSettings | None = None
        """The load (a table turns it on; without it, full buffer): per direction each UE's
        ``full-buffer``, ``ftp3`` (``ftp = { file_bytes, arrival_rate_hz }``) or ``none``, and
        the twin's messages it carries (``carry = [{ topic, direction, deliver_to }]``); the
        scheduler serves queued bytes only, and each completed transfer goes on
        ``network.transfers`` (:mod:`~caviar_plugins.network.traffic`)."""
        radio_map: RadioMapSettings | None = None
        """A best-server SINR map of ``raytracing.scene`` at setup (a table turns it on):
        ``cell_size_m``, ``height_m``, ``margin_m``, ``samples_per_tx``, ``max_depth`` (see
        :class:`~caviar_plugins.network.radio_map.RadioMapSettings`); written to
        ``radio-map.npz`` and ``radio-map.png`` and announced on ``network.radio_map``."""

        def __post_init__(self):
            if self.channel not in CHANNELS:
                raise ValueError(f"channel: expected one of {list(CHANNELS)}, got {self.channel!r}")
            self.cells: list[Cell] = deployment(self)
            if isinstance(self.report_cells, bool) or self.report_cells < 0:
                raise ValueError(f"report_cells: expected a number of cells >= 0, got {self.report_cells!r}")
            for c in self.cells:
                check_nr_carrier(c.carrier_hz, carrier_key(self, c))
            if self.beams is not None:
                if self.channel not in ("free-space", "ray-traced"):
                    raise ValueError(f"beams: need the channel's path directions, which the free-space and "
                                     f"ray-traced channels have; got channel = {self.channel!r}")
                self.codebooks = [self.beams.codebook(c.array) for c in self.cells]
            if self.interference not in INTERFERENCE:
                raise ValueError(f"interference: expected one of {list(INTERFERENCE)}, got {self.interference!r}")
            if self.num_prb is None:
                self.num_prb = nr_prbs(self.bandwidth_hz, self.subcarrier_spacing_hz)
                if self.num_prb is None:
                    raise ValueError(f"num_prb: {self.bandwidth_hz:g} Hz at {self.subcarrier_spacing_hz:g} Hz "
                                     f"spacing is not an NR channel bandwidth; give num_prb")
            if self.num_prb * 12 * self.subcarrier_spacing_hz > self.bandwidth_hz:
                raise ValueError(f"num_prb: {self.num_prb} PRBs of {12 * self.subcarrier_spacing_hz:g} Hz do not "
                                 f"fit in bandwidth_hz = {self.bandwidth_hz:g}")
            flat = self.channel != "ray-traced" or self.raytracing.evolve == "hold"
            self.link = LinkSettings(num_prb=self.num_prb, subcarrier_spacing_hz=self.subcarrier_spacing_hz,
                                     bler_target=self.bler_target, mcs_table=self.mcs_table,
                                     scheduler=self.scheduler, link_model=self.link_model,
                                     harq_processes=self.harq_processes, subbands=1 if flat else self.subbands,
                                     compile=self.compile, cuda_graphs=self.cuda_graphs, device=self.device)

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.p = p
        self.cells = p.cells
        self.names = [c.name for c in self.cells]
        self.slot_s = p.link.slot_s
        self.slots = max(1, round(ctx.ts * ctx.every / self.slot_s))
        if self.slots % p.harq_processes:
            raise caviar.ConfigError(f"a step of {ctx.ts * ctx.every:g} s is {self.slots} slots of {self.slot_s:g} s, "
                                     f"not whole groups of harq_processes = {p.harq_processes}",
                                     "params.harq_processes")
        self.mm = MobilityManager(p.handover, self.names)
        self.link = LinkLevel(p.link, len(self.cells), seed=ctx.seed)
        self.ul_link = None if p.uplink is None else LinkLevel(
            dataclasses.replace(p.link, direction="uplink", mcs_table=p.uplink.mcs_table), len(self.cells),
            seed=ctx.seed + 1)
        self.queues = None if p.traffic is None or p.traffic.full_buffer else Queues(p.traffic, ctx.seed)
        self.lost: list = []  # transfers of UEs that left, to report
        self.ues = UeTable()  # UE_Id -> column and type; per column, position, last SINR...
        self.bandwidths = np.array([c.bandwidth_hz for c in self.cells])
        self.tracer = None
        if p.channel == "ray-traced":
            self.tracer = SiteTracer(p.raytracing, self.cells, seed=ctx.seed, base_dir=ctx.config_dir)
            if p.layout is not None:
                covered = [c.site for c in self.cells if not self.tracer.outdoors(np.array([c.position]))[0]]
                if covered:
                    raise caviar.ConfigError(
                        f"the layout puts site(s) {', '.join(dict.fromkeys(covered))} under a roof of "
                        f"{p.raytracing.scene!r} (no open sky above {p.layout.height_m:g} m): move the layout "
                        f"with layout.center_m (now {list(p.layout.center_m)})", "params.layout.center_m")
        self.map_files: list = []
        self.layer: dict | None = None
        if p.radio_map is not None:
            result = best_server_map(self.cells, p.radio_map, p.raytracing.scene, p.num_prb,
                                     p.noise_figure_db, base_dir=ctx.config_dir, seed=ctx.seed)
            self.map_files = save(result, self.cells, ctx.run_dir)
            self.layer = layer_message(result, self.map_files[-1].relative_to(ctx.run_dir).as_posix(),
                                       height_m=p.radio_map.height_m)
        self.frequencies = p.link.subband_frequencies_hz
        # One subband: the band's power averaged over 8 frequencies, not one point's fade.
        self.band_average = len(self.frequencies) == 1
        if self.band_average:
            self.frequencies = dataclasses.replace(p.link, subbands=min(8, p.num_prb)).subband_frequencies_hz
        self.channels: TracedChannels | None = None  # the last trace, rows in self.traced order
        self.responses: tuple[TracedChannels | None, Any] = (None, None)  # (a trace, its paths' beam responses)
        self.traced: dict[str, int] = {}  # UE_Id -> row of self.channels
        self._rows: tuple[Any, np.ndarray] = (None, np.zeros(0, dtype=np.int64))  # (ids, their rows) of the trace
        self.refreshed_at = -np.inf  # the last refresh on the refresh_s schedule
        self.stochastic: StochasticChannel | None = None
        if p.channel in STOCHASTIC:
            wrap = Wraparound(p.layout) if p.layout is not None and p.layout.wraparound else None
            self.stochastic = StochasticChannel(STOCHASTIC[p.channel], self.cells, p.tr38901, wrap,
                                                device=p.device, seed=ctx.seed)
        self.drops = 0  # drops made (the layout's UEs)
        if p.layout is not None and p.layout.ues_per_sector:
            self._drop()

    def _forget(self, u: str) -> None:
        """What the network knew of UE ``u``'s radio: its handover state, its link level's
        column (the column itself stays ``u``'s), its 38.901 draw and its queues (their
        unfinished transfers are reported lost)."""
        self.mm.forget_row(self.ues.column(u))
        if self.queues is not None:
            self.lost += self.queues.forget(u)
        for link in (self.link, self.ul_link):
            if link is not None:
                link.released(self.ues.column(u))
        self.ues.last_sinr[self.ues.column(u)] = np.nan
        self.traced.pop(u, None)  # (traced again where it next is)
        self._rows = (None, self._rows[1])
        if self.stochastic is not None:
            self.stochastic.forget(u)

    def _drop(self) -> None:
        """A drop of the layout's UEs (TR 38.901 §7.8): ``drop<k>``, each a new UE. In a
        ray-traced scene a UE dropped under a roof is dropped again in its sector until it
        is outdoors (uniform over the sector's open ground)."""
        from sionna.phy import config as sionna_config

        layout = self.p.layout
        assert layout is not None
        scenario = layout.scenario or STOCHASTIC.get(self.p.channel, "uma")
        sionna_config.seed = (self.ctx.seed * 1_000_003 + self.drops) % 2**31  # (Sionna draws the drop)
        drop = drop_ues(layout, scenario, self.p.carrier_hz)
        if self.tracer is not None:
            inside = ~self.tracer.outdoors(drop.positions)
            for again in range(1, MAX_REDROPS + 1):
                if not inside.any():
                    break
                sionna_config.seed = (self.ctx.seed * 1_000_003 + self.drops + 7_919 * again) % 2**31
                more = drop_ues(layout, scenario, self.p.carrier_hz).positions  # (the same sectors, k by k)
                drop.positions[inside] = more[inside]
                inside[inside] = ~self.tracer.outdoors(more[inside])
            if inside.any():
                sectors = sorted({self.names[k // layout.ues_per_sector] for k in np.flatnonzero(inside)})
                raise caviar.ConfigError(f"{MAX_REDROPS} drops found no open ground in sector(s) {', '.join(sectors)} "
                                         f"of {self.p.raytracing.scene!r}: move the layout with layout.center_m",
                                         "params.layout.center_m")
        self.drops += 1
        cols = np.empty(len(drop.positions), dtype=np.int64)
        for k in range(len(drop.positions)):
            u = f"drop{k}"
            if u in self.ues:  # a fresh UE in the same column
                self._forget(u)
                cols[k] = self.ues.column(u)
            else:
                cols[k] = self.ues.add(u, "dropped")
        # The drop gives antenna heights (floors): no antenna_height_m on top.
        self.ues.position[cols], self.ues.lift[cols] = drop.positions, 0.0
        self.ues.indoor[cols], self.ues.distance_2d_in[cols] = drop.indoor, drop.distance_2d_in

    def state(self):
        # Cells, tracer and radio map come from setup (the map's files are written again);
        # what it still had to announce, the UEs, handover state, link level and the last
        # trace (the channels evolve from it until the next refresh) are the state.
        return {"map_files": [f.relative_to(self.ctx.run_dir).as_posix() for f in self.map_files],
                "layer": self.layer, "ues": self.ues.state(),
                "handover": self.mm.state(), "link": self.link.state(), "channels": self.channels,
                "ul_link": None if self.ul_link is None else self.ul_link.state(),
                "traced": self.traced, "refreshed_at": self.refreshed_at, "drops": self.drops,
                "stochastic": None if self.stochastic is None else self.stochastic.snapshot(),
                "cache_seen": self.tracer is not None and self.tracer.cache_seen(),
                "queues": None if self.queues is None else self.queues.state(), "lost": self.lost}

    def restore(self, state):
        self.map_files = [self.ctx.run_dir / f for f in state["map_files"]]
        self.layer = state["layer"]
        self.ues.restore(state["ues"])
        self.mm.restore(state["handover"])
        self.link.restore(state["link"])
        if self.ul_link is not None:
            self.ul_link.restore(state["ul_link"])
        self.channels, self.traced, self.refreshed_at = state["channels"], state["traced"], state["refreshed_at"]
        self._rows = (None, self._rows[1])
        self.drops, self.lost = state["drops"], state["lost"]
        if self.queues is not None:
            self.queues.restore(state["queues"])
        if self.stochastic is not None:
            self.stochastic.restore(state["stochastic"])
        if state.get("cache_seen") and self.tracer is not None and self.channels is not None:
            # The shoot cache had seen the scene: one trace where the UEs last were lets it see
            # it again (its result is not used), so the next trace is served as it would have been.
            self.tracer.trace(self.channels.position)

    def _traced_rows(self, ids: list[str]) -> np.ndarray:
        """The rows of the last trace of ``ids`` (looked up again only when the UEs change)."""
        if self._rows[0] is not ids:
            self._rows = (ids, np.array([self.traced[u] for u in ids], dtype=np.int64))
        return self._rows[1]

    def _channel_gains(self, t: float, ids: list[str], cols: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Channel gains (path and sector pattern, dB) of every cell toward the UEs
        ``ids`` at ``pos``: [n_ue, n_cell, subbands]. Ray-traced paths are refreshed every
        ``raytracing.refresh_s`` (and when a UE appears) and evolve in between."""
        if self.stochastic is not None:
            return self.stochastic.gains_db(ids, pos, self.ues.indoor[cols] > 0,
                                            self.ues.distance_2d_in[cols])[..., None]
        if self.tracer is None:
            return line_of_sight_gain_db(self.cells, pos)[..., None]
        due = t - self.refreshed_at >= self.p.raytracing.refresh_s - 1e-9
        if due or (self._rows[0] is not ids and any(u not in self.traced for u in ids)):
            self.channels = self.tracer.trace(pos)  # (a new UE is traced, with all, at once)
            self.traced = {u: i for i, u in enumerate(ids)}
            self._rows = (ids, np.arange(len(ids)))
            if due:
                self.refreshed_at = t
        assert self.channels is not None
        ch = self.channels.rows(self._traced_rows(ids))
        if self.p.raytracing.evolve == "hold":
            return ch.power_sum_db[..., None]
        self.amplitude = ch.amplitudes_on(self.p.device, pos, self.frequencies)  # (the beams' too; once a step)
        gains = summed_db(self.amplitude)
        if self.band_average:
            return 10 * np.log10(np.mean(10 ** (gains / 10), axis=-1, keepdims=True))
        return gains

    def _beam_gains(self, ids: list[str], pos: np.ndarray) -> np.ndarray:
        """[ue, cell, subband, beam]: every cell's SSB beams toward the UEs (linear), from the straight
        line or the paths :meth:`_channel_gains` just moved (their beam responses kept until the next trace)."""
        if self.tracer is None:
            amplitude, departure = line_of_sight(self.cells, pos)
            return all_beam_gains(self.cells, self.p.codebooks, amplitude[..., None], departure)
        ch = self.channels
        assert ch is not None and ch.departure is not None
        if self.responses[0] is not ch:  # (kept on the device, from one trace to the next)
            self.responses = (ch, beam_responses(self.cells, self.p.codebooks, ch.departure, self.p.device))
        rows = self._traced_rows(ids)
        amplitude = ch.amplitude[rows][..., None] if self.p.raytracing.evolve == "hold" else self.amplitude
        gains = gains_of_responses(amplitude, self.responses[1], rows)
        if self.band_average:
            gains = gains.mean(axis=2, keepdims=True)
        return gains

    def _beamformed_sinr(self, serving: np.ndarray, talking: np.ndarray | None):
        """Per slot and subband, and wideband (the slots' mean), SINR and SIR with beams;
        the other cells point at the UEs they schedule among ``talking`` (None: all)."""
        assert self.beam_gains is not None
        ue = np.arange(len(serving))
        best = np.where(serving >= 0, self.best_beams[ue, np.maximum(serving, 0)], 0)
        pointed = serving if talking is None else np.where(talking, serving, -1)
        beams = slot_beams(pointed, best, len(self.cells), self.slots)
        bandwidth = self.bandwidths[np.maximum(serving, 0)]
        noise = 10 ** (noise_dbm(bandwidth, self.p.noise_figure_db) / 10)
        silent = self.p.interference == "scheduled"
        per_slot = slot_sinr_db(self.cells, self.beam_gains, serving, best, beams, noise, silent, self.p.device)
        weights = self.p.link.subband_prbs if self.beam_gains.shape[2] > 1 else np.ones(1)
        flat = np.average(self.beam_gains, axis=2, weights=weights)[:, :, None, :]
        with np.errstate(divide="ignore"):  # (no signal: -inf, reported as None)
            sinr, sir = (10 * np.log10(np.mean(10 ** (slot_sinr_db(self.cells, flat, serving, best, beams, n, silent,
                                                                   self.p.device)[:, :, 0] / 10), axis=0))
                         for n in (noise, np.zeros(len(serving))))
        return per_slot, sinr, sir

    def _read(self, t: float, inbox) -> None:
        """UEs that left free their column; positions update (and add) UEs; the messages the
        UEs carry are queued."""
        for m in inbox.on(ARRIVED):
            if m.data["UE_Id"] in self.ues:
                self._forget(m.data["UE_Id"])
                self.ues.pop(m.data["UE_Id"])
        position, lift = self.ues.position, self.ues.lift
        for m in inbox.on(POSITIONS):  # (one message a UE: its numbers into the arrays)
            ue_id = m.data["UE_Id"]
            if ue_id not in self.ues:
                col = self.ues.add(ue_id, m.data["UE_type"])
                position, lift = self.ues.position, self.ues.lift
                lift[col] = self.p.antenna_height_m
            p = m.data["position"]
            position[self.ues.column(ue_id)] = (p["x"], p["y"], p["z"])
        if self.queues is not None:
            for c in self.p.traffic.carry:
                for m in inbox.on(c.topic):
                    sender = m.data["UE_Id"] if isinstance(m.data, dict) and "UE_Id" in m.data else ue_of(m.topic)
                    if sender not in self.ues:
                        raise ValueError(f"traffic.carry: a message on {m.topic} is for UE {sender!r}, which has no "
                                         f"position on {POSITIONS} (a UE must be placed to carry it)")
                    self.queues.queue_message(t if m.time is None else m.time, sender, m.topic, m.data, c)

    def _measure(self, t: float, ids: list[str], cols: np.ndarray):
        """Received power of every cell at every UE (per subband, and wideband) and RSRP;
        mobility management on them, all UEs at once. Returns (rx dBm [ue, cell, subband],
        wideband rx dBm [ue, cell], RSRP dBm, serving cell per UE, events)."""
        pos = self.ues.position[cols]
        pos[:, 2] += self.ues.lift[cols]
        gains = self._channel_gains(t, ids, cols, pos)
        rx = rx_power_dbm(self.cells, gains)
        weights = self.p.link.subband_prbs if gains.shape[-1] > 1 else np.ones(1)
        wideband = 10 * np.log10(np.average(10 ** (rx / 10), axis=-1, weights=weights))
        self.beam_gains = None
        if self.p.beams is not None:  # L1-RSRP: the best SSB beam's
            self.beam_gains = self._beam_gains(ids, pos)
            tx = np.array([c.tx_power_dbm for c in self.cells])[None, :]
            per_beam = 10 * np.log10(np.maximum(np.average(self.beam_gains, axis=2, weights=weights), 1e-40))
            wideband = tx + per_beam.max(axis=-1)
            self.best_beams = per_beam.argmax(axis=-1)  # [ue, cell]
        rsrp = rsrp_dbm(self.cells, wideband, [self.p.num_prb] * len(self.cells))
        self.mm.ensure(int(cols.max()) + 1)
        old = self.mm.serving_cell[cols]  # (a copy)
        events = self.mm.update_rows(t, cols, ids, rsrp, self.ues.last_sinr[cols])
        serving = self.mm.serving_cell[cols]
        for k in np.flatnonzero((old >= 0) & (serving >= 0) & (serving != old)).tolist():  # (handed over)
            for link in (self.link, self.ul_link):
                if link is not None:
                    link.moved(int(cols[k]), int(serving[k]))
        return rx, wideband, rsrp, serving, events

    def step(self, t, inbox):
        while self.map_files:
            yield NETWORK_RADIO_MAP, caviar.Artifact(self.map_files.pop(0))
        if self.layer is not None:
            yield VIEW_RADIO_MAP, self.layer
            self.layer = None
        self._read(t, inbox)
        if self.drops and t > 0 and self.p.layout is not None and self.p.layout.redrop == "every-step":
            self._drop()
        if not self.ues:
            return
        ids, cols, types = self.ues.view()
        rx, wideband, rsrp, serving, events = self._measure(t, ids, cols)
        backlog, talking = self._backlog(t, ids, types, "downlink")
        per_slot, sinr, sir = self._downlink_sinr(rx, wideband, serving, talking)
        sinr_cols, serving_cols = self._columns(per_slot, serving, cols)
        res = self.link.run(sinr_cols, serving_cols, backlog=in_columns(backlog, cols))
        mbps = res.throughput_bps(self.slots, self.slot_s) / 1e6
        yield from ((NETWORK_EVENTS, e) for e in events)
        yield from self._delivered(t, ids, "downlink", res.delivered_bits[:, cols])
        ul = None
        if self.ul_link is not None:
            ul = yield from self._uplink(t, ids, types, rx, serving, cols)
        covered = serving >= 0
        self.ues.last_sinr[cols] = np.where(covered, sinr, np.nan)
        sv = np.maximum(serving, 0)
        loss = np.array([c.tx_power_dbm for c in self.cells])[sv] - wideband[np.arange(len(ids)), sv]
        listed = None
        if self.p.report_cells:
            listed = np.sort(np.argsort(-rsrp, axis=1, kind="stable")[:, :self.p.report_cells], axis=1)
        link = link_fields(res, cols) if self.p.link_model == "sys" else None
        yield from ue_reports(self.names, ids, types, serving, sinr, sir, loss, rsrp, listed, mbps[cols], link,
                              self._extras(ids, types, serving, ul), self.ues.position[cols])
        used = res.cells_active.mean(axis=0)
        counts = np.bincount(serving[covered], minlength=len(self.cells)).tolist()
        yield NETWORK_CELLS, {"cells": [
            {"cell": n, "ues": counts[k], "active_share": round(float(used[k]), 4)}
            for k, n in enumerate(self.names)]}

    def _downlink_sinr(self, rx: np.ndarray, wideband: np.ndarray, serving: np.ndarray, talking: np.ndarray | None):
        """Per slot and subband [slot or 1, ue, subband], and wideband [ue], SINR and SIR; with
        ``interference = "scheduled"`` only cells with data for someone (``talking``) send."""
        if self.p.beams is not None:
            return self._beamformed_sinr(serving, talking)
        load = None
        if self.p.interference == "scheduled":
            on = serving if talking is None else serving[talking]
            load = np.isin(np.arange(len(self.cells)), on).astype(float)
        sinr = sinr_db(self.cells, wideband, serving, self.p.noise_figure_db, load)
        sir = sinr_db(self.cells, wideband, serving, -np.inf, load)
        return sinr_db(self.cells, rx, serving, self.p.noise_figure_db, load)[None], sinr, sir

    def _extras(self, ids: list[str], types: list[str], serving: np.ndarray, ul):
        """``extras(i, covered)``: UE ``i``'s ``network.ue`` fields beyond the downlink's (uplink,
        beam, queues), from the step's arrays."""
        beams: list[dict] | None = None
        if self.p.beams is not None:  # (each cell's beams' reports, made once)
            if not hasattr(self, "_beam_reports"):
                self._beam_reports = [[beam_report(c, cb, b) for b in range(cb.size)]
                                      for c, cb in zip(self.cells, self.p.codebooks, strict=True)]
            sv = np.maximum(serving, 0)
            beams = [self._beam_reports[s][b] for s, b in
                     zip(sv.tolist(), self.best_beams[np.arange(len(sv)), sv].tolist(), strict=True)]
        directions = ("downlink", "uplink") if self.ul_link else ("downlink",)

        def extras(i: int, covered: bool) -> dict[str, Any]:
            out: dict[str, Any] = {}
            if ul is not None and covered:
                out.update(ul[i])
            if beams is not None and covered:
                out.update(beams[i])
            if self.queues is not None:
                out.update(self.queues.report(ids[i], types[i], directions))
            return out
        return extras

    def _columns(self, per_slot: np.ndarray, serving: np.ndarray, cols: np.ndarray):
        """A link level's inputs on UE columns (stable across steps): SINR [slot, column,
        subband] over the step's slots (one row: every slot), and the serving cells."""
        sinr_cols = np.full((len(per_slot), int(cols.max()) + 1, per_slot.shape[2]), np.nan)
        serving_cols = np.full(int(cols.max()) + 1, -1)
        sinr_cols[:, cols], serving_cols[cols] = per_slot, serving
        return np.broadcast_to(sinr_cols, (self.slots, *sinr_cols.shape[1:])), serving_cols

    def _backlog(self, t: float, ids: list[str], types: list[str], direction: str):
        """The step's queued and arriving bits of ``ids`` in ``direction`` (None: full buffer)
        and, with ``interference = "scheduled"``, which UEs have any: the only ones their cells
        transmit to or receive from ([ue] bool; None: all, as under full-buffer interference)."""
        if self.queues is None or all(self.queues.model(direction, k) == "full-buffer" for k in set(types)):
            return None, None
        backlog = self.queues.backlog(t, ids, types, direction, self.slots, self.slot_s)
        if self.p.interference != "scheduled":
            return backlog, None  # (every cell transmits, whatever its queues)
        return backlog, (backlog.queued_bits > 0) | (backlog.arrivals_bits > 0).any(axis=0)

    def _delivered(self, t: float, ids: list[str], direction: str, delivered_bits: np.ndarray):
        """Takes the step's delivered bits ([slot, ue]) off the queues: every transfer completed
        (and what its UEs left unfinished) on ``network.transfers``, and each carried message
        delivered on its ``deliver_to`` topic."""
        if self.queues is None:
            return
        for x in self.lost:
            yield NETWORK_TRANSFERS, transfer_record(x, None)
        self.lost = []
        for x, done in self.queues.serve(t, ids, direction, delivered_bits, self.slot_s):
            yield NETWORK_TRANSFERS, transfer_record(x, done)
            if x.deliver_to is not None:
                yield f"{x.deliver_to}.{x.ue}", x.payload

    def _uplink(self, t: float, ids: list[str], types: list[str], rx: np.ndarray, serving: np.ndarray,
                cols: np.ndarray):
        """The step's PUSCH: powers, per-slot SINR, the uplink link level, the transfers it
        completed (yielded); returns every UE's ``ul_*`` fields, a list."""
        assert self.p.uplink is not None and self.ul_link is not None
        backlog, talking = self._backlog(t, ids, types, "uplink")
        tx, per_slot = uplink(self.cells, self.p.uplink, serving, rx, self.beam_gains,
                              getattr(self, "best_beams", None) if self.p.beams else None, self.p.num_prb,
                              self.p.subcarrier_spacing_hz, self.slots, self.p.device, talking)
        sinr_cols, serving_cols = self._columns(per_slot, serving, cols)
        res = self.ul_link.run(sinr_cols, serving_cols, backlog=in_columns(backlog, cols))
        yield from self._delivered(t, ids, "uplink", res.delivered_bits[:, cols])
        mbps = res.throughput_bps(self.slots, self.slot_s) / 1e6
        with np.errstate(divide="ignore"):  # (a UE whose paths to its cell are gone: no signal)
            mean = 10 * np.log10(np.mean(10 ** (per_slot / 10), axis=(0, 2)))
        return uplink_fields(tx, mean, mbps[cols], link_fields(res, cols))
