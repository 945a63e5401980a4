"""What a link level's call gives each UE over its slots (:class:`SlotResults`), and the tally
that makes it from the call's groups of slots, every link at once (:func:`tallied`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from caviar_plugins.radio.link_queue import CallQueue
from caviar_plugins.torch_device import to_numpy


@dataclasses.dataclass
class SlotResults:
    """What a UE got over the slots of one call."""

    decoded_bits: np.ndarray  # [n_ue] summed over the slots
    scheduled_slots: np.ndarray  # [n_ue] slots with at least one PRB
    prbs: np.ndarray  # [n_ue] PRB-slots allocated
    acks: np.ndarray  # [n_ue]
    nacks: np.ndarray  # [n_ue]
    mcs: np.ndarray  # [n_ue] the last MCS used (-1: never scheduled)
    tbler: np.ndarray  # [n_ue] mean TBLER over scheduled slots (NaN: none)
    sinr_eff_db: np.ndarray  # [n_ue] the last effective SINR (NaN: none)
    cells_active: np.ndarray  # [n_slots, n_cell] cells that scheduled someone
    delivered: Any  # [n_slots, n_ue] bits decoded per slot (of the UE's queue), or what reads them (once)

    @property
    def delivered_bits(self) -> np.ndarray:
        """[n_slots, n_ue]: the bits each slot delivered of each UE's queue (read from the device
        when first asked for: a full buffer's network step never asks, so never copies them out)."""
        if callable(self.delivered):
            self.delivered = self.delivered()
        return self.delivered

    def bler(self, ue: int) -> float:
        return self.nacks[ue] / max(self.acks[ue] + self.nacks[ue], 1)

    def throughput_bps(self, n_slots: int, slot_s: float) -> np.ndarray:
        return self.decoded_bits / (n_slots * slot_s)

    def summary(self, u: int) -> dict[str, Any]:
        return {"mcs": int(self.mcs[u]),
                "tbler": None if np.isnan(self.tbler[u]) else round(float(self.tbler[u]), 4),
                "harq_ack": int(self.acks[u]), "harq_nack": int(self.nacks[u]),
                "prbs": int(self.prbs[u])}


RESULTS = tuple(f.name for f in dataclasses.fields(SlotResults) if f.name != "delivered") + ("delivered_bits",)
"""A :class:`SlotResults`' results by name (``delivered_bits`` read when asked for)."""


def no_slots(n_ue: int, n_slots: int, n_cell: int) -> SlotResults:
    """A call's results where no slot ran."""
    zeros = np.zeros(n_ue, dtype=int)
    return SlotResults(np.zeros(n_ue), zeros, zeros, zeros, zeros, np.full(n_ue, -1), np.full(n_ue, np.nan),
                       np.full(n_ue, np.nan), np.zeros((n_slots, n_cell), dtype=bool), np.zeros((n_slots, n_ue)))


def tallied(torch: Any, groups: list[tuple], queues: list[CallQueue], n_slots: int, n_ue: int,
            n_cell: int) -> list[SlotResults]:
    """Each link's results from a link level's call, its runs of slots (``(first slot, slots, PRBs,
    HARQ, TBLER, MCS, effective SINR, cells active, decoded bits, tallies)``, each [L, slots, ...],
    the tallies :func:`per_ue` of the slots up to the run's last, :func:`carried` from run to run,
    or None: see :meth:`~caviar_plugins.radio.link_level.LinkLevel._groups_at`): tallied on the
    device, every link at once (where every slot ran in runs that carry their tallies: the last
    run's, no torch operation more), then the call's one way out."""
    if not groups:
        return [no_slots(n_ue, n_slots, n_cell) for _ in queues]
    dev, n_links = groups[0][2].device, groups[0][2].shape[0]
    every = sum(g[1] for g in groups) == n_slots  # (every slot ran: in order)
    slots = None if every else torch.cat([torch.arange(g[0], g[0] + g[1], device=dev) for g in groups])
    if every and all(g[9] is not None for g in groups):  # (compiled calls of every slot: tallied there, carried on)
        cells, bits = ([g[i] for g in groups] for i in (7, 8))
        active, bits = (x[0] if len(x) == 1 else torch.cat(x, dim=1) for x in (cells, bits))
        per_ue_t = groups[-1][9]
    else:
        fields = list(zip(*groups, strict=True))[2:9]  # (each [L, slots run, cap]; cells: [L, slots run, C])
        prbs, harq, tbler, mcs, sinr_eff, cells, bits = (torch.cat(x, dim=1) for x in fields)
        active = cells
        if not every:
            active = torch.zeros((n_links, n_slots, n_cell), dtype=torch.bool, device=dev)
            active[:, slots] = cells
        per_ue_t = per_ue(torch, prbs, harq, tbler, mcs, sinr_eff, bits)
    if any(q.finite for q in queues):  # (a full buffer delivers all it decodes; a queue what it took of it)
        per_ue_t[:, 7] = torch.stack([torch.sum(q.delivered, dim=0) if q.finite else d
                                      for q, d in zip(queues, per_ue_t[:, 7], strict=True)])
    # (the call's one way out: every tally, as float64 (the counts exact in it), in one read; the
    # bits of each slot stay where they are until asked for)
    out = to_numpy(torch.cat([per_ue_t.flatten(), active.flatten()]))
    tallies = out[:per_ue_t.numel()].reshape(per_ue_t.shape)[:, :, :n_ue]
    active_n = out[per_ue_t.numel():].reshape(active.shape) != 0
    results = []
    for per, act, q, link_bits in zip(tallies, active_n, queues, bits, strict=True):
        sched_n, prbs_n, acks_n, nacks_n = per[:4].astype(np.int64)
        tbler_n, mcs_n, eff_n, decoded_n = per[4:]
        with np.errstate(invalid="ignore", divide="ignore"):
            tbler_mean = np.where(sched_n > 0, tbler_n / sched_n, np.nan)
        reader = _reader(torch, q.delivered, None, n_slots, n_ue) if q.finite else \
            _reader(torch, link_bits, slots, n_slots, n_ue)
        results.append(SlotResults(decoded_n, sched_n, prbs_n, acks_n, nacks_n, mcs_n.astype(np.int64),
                                   tbler_mean, eff_n, act, reader))
    return results


def no_tallies(torch: Any, n_links: int, capacity: int, device: Any) -> Any:
    """[L, 8, cap]: :func:`per_ue`'s tallies of no slot (nothing counted, no MCS, no SINR): where
    :func:`carried` starts."""
    none = torch.zeros((n_links, 8, capacity), dtype=torch.float64, device=device)
    none[:, 5], none[:, 6] = -1.0, float("nan")
    return none


def carried(torch: Any, before: Any, run: Any) -> Any:
    """[L, 8, cap]: the tallies :func:`per_ue` of slots ``before`` (:func:`no_tallies`: none) and then
    of a ``run`` of slots after them: the counts and sums added, the last MCS and SINR the run's
    where it scheduled the UE."""
    added = before + run
    last = torch.where((run[:, 0] > 0)[:, None], run[:, 5:7], before[:, 5:7])
    return torch.cat([added[:, :5], last, added[:, 7:]], dim=1)


def per_ue(torch: Any, prbs: Any, harq: Any, tbler: Any, mcs: Any, sinr_eff: Any, bits: Any) -> Any:
    """[L, 8, cap] float64 (the counts exact in it): each UE's tallies over a run of slots (each
    field [L, slots, cap]): slots scheduled, PRB-slots, ACKs, NACKs, the TBLERs of its scheduled
    slots summed, its last scheduled slot's MCS (-1: none) and effective SINR in dB (NaN: none), and
    the bits decoded. Torch operations only: a compiled call of several groups makes them in its own
    program, carried from call to call (:meth:`~caviar_plugins.radio.link_level.LinkLevel._groups_eager`)."""
    sched = prbs > 0  # [L, slots, cap]
    # the last scheduled slot's MCS and effective SINR
    last = sched.shape[1] - 1 - torch.argmax(torch.flip(sched, (1,)).to(torch.uint8), dim=1)[:, None]  # [L,1,cap]
    anyone = sched.any(dim=1)
    mcs_last = torch.where(anyone, mcs.to(torch.int64).gather(1, last)[:, 0], -1)
    eff_db = 10 * torch.log10(torch.clamp(sinr_eff.to(torch.float64).gather(1, last)[:, 0], min=1e-30))
    sinr_eff_last = torch.where(anyone, eff_db, float("nan"))
    tbler_sum = torch.where(sched, tbler.to(torch.float64), 0.0).sum(dim=1)
    decoded = bits.to(torch.float64).sum(dim=1)  # [L, cap]
    return torch.stack([sched.sum(dim=1), prbs.sum(dim=1), (harq == 1).sum(dim=1), (harq == 0).sum(dim=1),
                        tbler_sum, mcs_last, sinr_eff_last, decoded], dim=1).to(torch.float64)


def _reader(torch: Any, bits: Any, slots: Any, n_slots: int, n_ue: int) -> Any:
    """What reads one link's bits of each slot to the host when asked, [n_slots, n_ue] float64:
    ``bits`` [slots run, cap] on the device (``slots``: the slots they are, None: every slot in
    order; a slot that did not run delivered nothing)."""
    def read() -> np.ndarray:
        b = bits.to(torch.float64)
        if slots is not None:
            placed = torch.zeros((n_slots, b.shape[1]), dtype=torch.float64, device=b.device)
            placed[slots] = b
            b = placed
        return to_numpy(b)[:, :n_ue]
    return read
