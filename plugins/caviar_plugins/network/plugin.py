"""``radio-network``: a multi-cell radio network in the loop.

Every UE that publishes a position (UAVs, SUMO cars and pedestrians) measures every
cell; it attaches to the strongest, hands over on the A3 event, fails its radio link
when its SINR stays too low, and gets what the link level gives it (Sionna SYS:
proportional-fair scheduling, outer-loop link adaptation, PHY abstraction on NR BLER
tables; or Shannon). Publishes per step:

- ``communications.throughput`` (the paper's schema, Mbit/s of decoded bits) per UE;
- ``network.ue`` per UE: serving cell, RSRP of every cell, SINR, SIR, coupling loss, MCS,
  TBLER, HARQ (and, for a UE the layout dropped, its position); with ``ue_reports = "table"``,
  ``network.ues`` instead, the same fields as one table a step (a ``polars.DataFrame``);
- ``network.events``: attach, handover and radio-link-failure events;
- ``network.cells``: per cell, its UEs and the share of PRB-slots it used.

The channel (``channel``, one model behind :class:`~caviar_plugins.network.channel.Channel`,
chosen at set-up; TR 38.901's stochastic models too): free space (Friis with the 3GPP sector pattern) or ray-traced
(Sionna RT, every site in one solve, the sector patterns applied per path; refreshed every
``evolution.refresh_s`` of virtual time). Between refreshes the ray-traced channel
evolves: as a UE moves, every path's phase turns by its displacement along the path's
direction of arrival (at the path's Doppler shift), evaluated at each step on
``subbands`` frequencies across the band, so the SINR fades in time and frequency and
the scheduler allocates per subband (``evolution.mode = "hold"`` freezes the paths'
power sum instead).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

import caviar
from caviar.topics import matches
from caviar_plugins.network.beams import beam_report
from caviar_plugins.network.channel import UePlaces
from caviar_plugins.network.downlink import received
from caviar_plugins.network.handover import MobilityManager
from caviar_plugins.network.layout import drop_outdoors
from caviar_plugins.network.radio_map import best_server_map, layer_message, save
from caviar_plugins.network.settings import NetworkParams, make_channel, plan
from caviar_plugins.network.sinrs import step_sinrs
from caviar_plugins.network.tr38901 import CHANNELS as STOCHASTIC
from caviar_plugins.network.traffic import Queues, in_columns, transfer_record
from caviar_plugins.network.ues import (
    UeTable,
    beam_columns,
    beam_table,
    link_fields,
    run_links,
    throughput_messages,
    ue_extras,
    ue_reports,
    ue_table,
    uplink_arrays,
    uplink_columns,
    uplink_fields,
)
from caviar_plugins.radio.link_level import LinkLevel
from caviar_plugins.schema import (
    ARRIVED,
    NETWORK_CELLS,
    NETWORK_EVENTS,
    NETWORK_RADIO_MAP,
    NETWORK_TRANSFERS,
    NETWORK_UE,
    NETWORK_UES,
    POSITIONS,
    THROUGHPUT,
    VIEW_RADIO_MAP,
    ue_of,
)
from caviar_plugins.torch_device import resolve


class RadioNetwork(caviar.Plugin):
    subscribe = [POSITIONS, ARRIVED]
    optional = (ARRIVED,)  # (UEs that leave: SUMO's arrivals, when traffic runs)
    publishes = (THROUGHPUT, NETWORK_EVENTS, NETWORK_CELLS, NETWORK_RADIO_MAP, VIEW_RADIO_MAP)
    Params = NetworkParams

    @classmethod
    def inputs(cls, params):
        """The topics ``traffic.carry`` names: their messages go over the network."""
        if params.traffic is None:
            return {}
        return {c.topic: f"params.traffic.carry.{i}.topic" for i, c in enumerate(params.traffic.carry)}

    @classmethod
    def outputs(cls, params):
        """The UEs' reports (``network.ue``, or ``network.ues`` with ``ue_reports = "table"``),
        ``network.transfers`` with a load, and where delivered messages go on."""
        reports = NETWORK_UES if params.ue_reports == "table" else NETWORK_UE
        if params.traffic is None:
            return (reports,)
        return (reports, NETWORK_TRANSFERS, *(f"{c.deliver_to}.*" for c in params.traffic.carry if c.deliver_to))

    def setup(self, ctx):
        self.ctx, p = ctx, ctx.params
        self.p = p
        made = plan(p)
        self.cells, self.codebooks, self.names = made.cells, made.codebooks, [c.name for c in made.cells]
        self.tx_power_dbm = np.array([c.tx_power_dbm for c in self.cells])
        self.beam_reports = None if made.codebooks is None else [  # (each cell's beams' network.ue fields)
            [beam_report(c, cb, b) for b in range(cb.size)] for c, cb in zip(self.cells, made.codebooks, strict=True)]
        self.beam_table = None if self.beam_reports is None else beam_table(self.beam_reports)  # (the table's)
        self.device = resolve(p.device)  # (once: the channel's, beams' and uplink's torch work runs there)
        link = made.link  # (each link level resolves the same setting once, when it is made)
        self.slot_s = link.slot_s
        self.subband_prbs = link.subband_prbs
        self.slots = max(1, round(ctx.ts * ctx.every / self.slot_s))
        if self.slots % p.harq_processes:
            raise caviar.ConfigError(f"a step of {ctx.ts * ctx.every:g} s is {self.slots} slots of {self.slot_s:g} s, "
                                     f"not whole groups of harq_processes = {p.harq_processes}",
                                     "params.harq_processes")
        self.mm = MobilityManager(p.handover, self.names)
        # One link level for the downlink and the uplink (PUSCH, its MCS table): LinkLevel.run_links
        self.directions = ("downlink",) if p.uplink is None else ("downlink", "uplink")
        self.link = LinkLevel(link if p.uplink is None else
                              [link, dataclasses.replace(link, direction="uplink", mcs_table=p.uplink.mcs_table)],
                              len(self.cells), seed=ctx.seed)
        self.queues = None if p.traffic is None or p.traffic.full_buffer else Queues(p.traffic, ctx.seed)
        self.ues = UeTable()  # UE_Id -> column and type; per column, position, last SINR...
        self.channel = make_channel(p.channel, p, self.cells, link=link, device=self.device, seed=ctx.seed,
                                    base_dir=ctx.config_dir)
        self.map_files: list = []
        self.layer: dict | None = None
        if p.radio_map is not None:
            result = best_server_map(self.cells, p.radio_map, p.scene, p.num_prb,
                                     p.noise_figure_db, base_dir=ctx.config_dir, seed=ctx.seed)
            self.map_files = save(result, self.cells, ctx.run_dir)
            self.layer = layer_message(result, self.map_files[-1].relative_to(ctx.run_dir).as_posix(),
                                       height_m=p.radio_map.height_m)
        self.drops = 0  # drops made (the layout's UEs)
        if p.layout is not None and p.layout.ues_per_sector:
            self._drop()

    def _forget(self, u: str) -> None:
        """What the network knew of UE ``u``'s radio: its handover state, its link level's
        column (the column itself stays ``u``'s), its channel and its queues (their
        unfinished transfers are reported lost)."""
        col = self.ues.column(u)
        self.mm.forget_row(col)
        if self.queues is not None:
            self.queues.forget(u)
        self.link.released(col)
        self.ues.last_sinr[col] = np.nan
        self.channel.forget(u)

    def _drop(self) -> None:
        """A drop of the layout's UEs (TR 38.901 §7.8): ``drop<k>``, each a new UE, outdoors
        where the channel has a scene (:func:`~caviar_plugins.network.layout.drop_outdoors`)."""
        layout = self.p.layout
        assert layout is not None
        scenario = layout.scenario or STOCHASTIC.get(self.p.channel, "uma")
        drop = drop_outdoors(layout, scenario, self.p.carrier_hz, self.ctx.seed * 1_000_003 + self.drops,
                             self.channel.outdoors, self.names)
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
        # Cells, channel model and radio map come from setup (the map's files are written
        # again); what it still had to announce, the UEs, handover state, link levels, the
        # channel's (the last trace, or the 38.901 draws) and the queues are the state.
        return {"map_files": [f.relative_to(self.ctx.run_dir).as_posix() for f in self.map_files],
                "layer": self.layer, "ues": self.ues.state(), "handover": self.mm.state(),
                "link": self.link.state(),
                "channel": self.channel.state(), "drops": self.drops,
                "queues": None if self.queues is None else self.queues.state()}

    def restore(self, state):
        self.map_files = [self.ctx.run_dir / f for f in state["map_files"]]
        self.layer, self.drops = state["layer"], state["drops"]
        self.ues.restore(state["ues"])
        self.mm.restore(state["handover"])
        self.link.restore(state["link"])
        if self.queues is not None:
            self.queues.restore(state["queues"])
        self.channel.restore(state["channel"])

    def _read(self, t: float, inbox) -> None:
        """UEs that left free their column; positions update (and add) UEs; the messages the
        UEs carry are queued."""
        others = [m for m in inbox if m.topic != POSITIONS]  # (the few that are not a UE's position)
        for m in others:
            if m.topic == ARRIVED and m.data["UE_Id"] in self.ues:
                self._forget(m.data["UE_Id"])
                self.ues.pop(m.data["UE_Id"])
        # (one message a UE: their numbers gathered by list, into the arrays at once)
        self.ues.place([m.data for m in inbox if m.topic == POSITIONS], self.p.antenna_height_m)
        if self.queues is not None:
            for i, c in enumerate(self.p.traffic.carry):
                for m in inbox.on(c.topic) if matches(c.topic, POSITIONS) else [m for m in others
                                                                                  if matches(c.topic, m.topic)]:
                    sender = m.data["UE_Id"] if isinstance(m.data, dict) and "UE_Id" in m.data else ue_of(m.topic)
                    if sender not in self.ues:
                        raise caviar.ConfigError(f"a message on {m.topic} is for UE {sender!r}, which has no "
                                                 f"position on {POSITIONS} (a UE must be placed to carry it)",
                                                 f"params.traffic.carry.{i}.topic")
                    try:
                        self.queues.queue_message(t if m.time is None else m.time, sender, m.topic, m.data, c)
                    except ValueError as e:  # (a payload without its size_field: the setting is wrong)
                        raise caviar.ConfigError(f"a message on {m.topic}: {str(e).partition(': ')[2]}",
                                                 f"params.traffic.carry.{i}.size_field") from None

    def _measure(self, t: float, ids: list[str], cols: np.ndarray):
        """Received power of every cell at every UE (per subband, and wideband) and RSRP;
        mobility management on them, all UEs at once. Returns (rx dBm [ue, cell, subband],
        wideband rx dBm [ue, cell], RSRP dBm, serving cell per UE, events)."""
        pos = self.ues.position[cols]
        pos[:, 2] += self.ues.lift[cols]
        places = UePlaces(ids, pos, self.ues.indoor[cols] > 0, self.ues.distance_2d_in[cols])
        gains = self.channel.gains_db(t, places)
        beam_gains = None if self.codebooks is None else self.channel.beam_gains(places, self.codebooks)
        rx, wideband, rsrp, best = received(self.cells, gains, self.subband_prbs, self.p.num_prb, beam_gains)
        # (the beam gains [ue, cell, subband, beam] and best beams [ue, cell]: L1-RSRP, the SINR's beams)
        self.beams = None if beam_gains is None or best is None else (beam_gains, best)
        self.mm.ensure(int(cols.max()) + 1)
        old = self.mm.serving_cell[cols]  # (a copy)
        events = self.mm.update_rows(t, cols, ids, rsrp, self.ues.last_sinr[cols])
        serving = self.mm.serving_cell[cols]
        for k in np.flatnonzero((old >= 0) & (serving >= 0) & (serving != old)).tolist():  # (handed over)
            self.link.moved(int(cols[k]), int(serving[k]))
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
        ul_backlog, ul_talking = (None, None) if self.p.uplink is None else self._backlog(t, ids, types, "uplink")
        per_slot, sinr, sir, ul_in = step_sinrs(self.p, self.cells, rx, wideband, serving, talking, ul_talking,
                                                self.beams, self.slots, self.subband_prbs, self.device)
        per_slots, backlogs = [per_slot], [in_columns(backlog, cols)]
        if ul_in is not None:  # (the uplink's powers, per-slot SINR and mean SINR)
            per_slots.append(ul_in[1])
            backlogs.append(in_columns(ul_backlog, cols))
        res, *ul_res = run_links(self.link, per_slots, serving, cols, self.slots, backlogs)  # (both directions at once)
        mbps = res.throughput_bps(self.slots, self.slot_s) / 1e6
        yield from ((NETWORK_EVENTS, e) for e in events)
        yield from self._delivered(t, ids, "downlink", res, cols)
        ul = None
        if ul_in is not None:
            ul = yield from self._uplink_out(t, ids, ul_res[0], ul_in[0], ul_in[2], cols)
        covered = serving >= 0
        self.ues.last_sinr[cols] = np.where(covered, sinr, np.nan)
        sv = np.maximum(serving, 0)
        loss = self.tx_power_dbm[sv] - wideband[np.arange(len(ids)), sv]
        listed = None
        if self.p.report_cells:
            listed = np.sort(np.argsort(-rsrp, axis=1, kind="stable")[:, :self.p.report_cells], axis=1)
        link = link_fields(res, cols) if self.p.link_model == "sys" else None
        best_beams = None if self.beams is None else self.beams[1]
        if self.p.ue_reports == "table":  # (the paper's per-UE throughput, then one table of the rest)
            yield from throughput_messages(ids, types, mbps[cols])
            beams = None if self.beam_table is None or best_beams is None else \
                beam_columns(self.beam_table, serving, best_beams)
            queued = [] if self.queues is None else self.queues.reports(ids, types, self.directions)
            yield NETWORK_UES, ue_table(self.names, ids, types, serving, sinr, sir, loss, rsrp, listed, mbps[cols],
                                        link, ul, beams, queued, self.ues.position[cols])
        else:
            ul_f = None if ul is None else uplink_fields(uplink_columns(ul))
            extras = ue_extras(ids, types, serving, ul_f, self.beam_reports, best_beams, self.queues, self.directions)
            yield from ue_reports(self.names, ids, types, serving, sinr, sir, loss, rsrp, listed, mbps[cols], link,
                                  extras, self.ues.position[cols])
        used = res.cells_active.mean(axis=0)
        counts = np.bincount(serving[covered], minlength=len(self.cells)).tolist()
        yield NETWORK_CELLS, {"cells": [{"cell": n, "ues": counts[k], "active_share": round(float(used[k]), 4)}
                                        for k, n in enumerate(self.names)]}

    def _backlog(self, t: float, ids: list[str], types: list[str], direction: str):
        """The step's queued and arriving bits of ``ids`` in ``direction`` (None: full buffer)
        and which UEs have any ([ue] bool; None: all): see :meth:`Queues.step_backlog`."""
        if self.queues is None:
            return None, None
        return self.queues.step_backlog(t, ids, types, direction, self.slots, self.slot_s,
                                        self.p.interference == "scheduled")

    def _delivered(self, t: float, ids: list[str], direction: str, res, cols: np.ndarray):
        """Takes the step's delivered bits (``res``' [slot, ue] of the UE columns ``cols``; a full
        buffer's are not read) off the queues: every transfer completed (and what its UEs left
        unfinished) on ``network.transfers``, and each carried message on its ``deliver_to`` topic."""
        if self.queues is None:
            return
        for x, done in self.queues.finished(t, ids, direction, res.delivered_bits[:, cols], self.slot_s):
            yield NETWORK_TRANSFERS, transfer_record(x, done)
            if done is not None and x.deliver_to is not None:
                yield f"{x.deliver_to}.{x.ue}", x.payload

    def _uplink_out(self, t: float, ids: list[str], res, tx: Any, sinr: np.ndarray, cols: np.ndarray):
        """The step's PUSCH after the link level (``res``): its completed transfers; every UE's ``ul_*`` fields."""
        yield from self._delivered(t, ids, "uplink", res, cols)
        mbps = res.throughput_bps(self.slots, self.slot_s) / 1e6
        return uplink_arrays(tx, sinr, mbps[cols], link_fields(res, cols))
