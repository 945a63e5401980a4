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
    delivered_bits: np.ndarray  # [n_slots, n_ue] bits decoded per slot (of the UE's queue)

    def bler(self, ue: int) -> float:
        return self.nacks[ue] / max(self.acks[ue] + self.nacks[ue], 1)

    def throughput_bps(self, n_slots: int, slot_s: float) -> np.ndarray:
        return self.decoded_bits / (n_slots * slot_s)

    def summary(self, u: int) -> dict[str, Any]:
        return {"mcs": int(self.mcs[u]),
                "tbler": None if np.isnan(self.tbler[u]) else round(float(self.tbler[u]), 4),
                "harq_ack": int(self.acks[u]), "harq_nack": int(self.nacks[u]),
                "prbs": int(self.prbs[u])}


def no_slots(n_ue: int, n_slots: int, n_cell: int) -> SlotResults:
    """A call's results where no slot ran."""
    zeros = np.zeros(n_ue, dtype=int)
    return SlotResults(np.zeros(n_ue), zeros, zeros, zeros, zeros, np.full(n_ue, -1), np.full(n_ue, np.nan),
                       np.full(n_ue, np.nan), np.zeros((n_slots, n_cell), dtype=bool), np.zeros((n_slots, n_ue)))


def tallied(torch: Any, groups: list[tuple], queues: list[CallQueue], n_slots: int, n_ue: int,
            n_cell: int) -> list[SlotResults]:
    """Each link's results from a link level's call, its runs of slots (``(first slot, PRBs,
    HARQ, TBLER, MCS, effective SINR, cells active, decoded bits)``, each [L, slots, ...]: see
    :meth:`~caviar_plugins.radio.link_level.LinkLevel._groups_at`): tallied on the device, every
    link at once, then the call's one way out."""
    if not groups:
        return [no_slots(n_ue, n_slots, n_cell) for _ in queues]
    dev, (n_links, _, cap) = groups[0][1].device, groups[0][1].shape
    fields = list(zip(*groups, strict=True))[1:]  # (each [L, slots run, cap]; cells: [L, slots run, C])
    prbs, harq, tbler, mcs, sinr_eff, cells, bits = (torch.cat(x, dim=1) for x in fields)
    every = sum(g[1].shape[1] for g in groups) == n_slots  # (every slot ran: in order)
    slots = None if every else torch.cat([torch.arange(g[0], g[0] + g[1].shape[1], device=dev) for g in groups])
    active = cells
    if not every:
        active = torch.zeros((n_links, n_slots, n_cell), dtype=torch.bool, device=dev)
        active[:, slots] = cells
    delivered = []
    for q, link_bits in zip(queues, bits, strict=True):
        if q.finite:
            delivered.append(q.delivered)
        elif every:  # (a full buffer delivers all it decodes)
            delivered.append(link_bits.to(torch.float64))
        else:
            placed = torch.zeros((n_slots, cap), dtype=torch.float64, device=dev)
            placed[slots] = link_bits.to(torch.float64)
            delivered.append(placed)
    sched = prbs > 0  # [L, slots run, cap]
    # the last scheduled slot's MCS and effective SINR
    last = sched.shape[1] - 1 - torch.argmax(torch.flip(sched, (1,)).to(torch.uint8), dim=1)[:, None]  # [L,1,cap]
    anyone = sched.any(dim=1)
    mcs_last = torch.where(anyone, mcs.to(torch.int64).gather(1, last)[:, 0], -1)
    eff_db = 10 * torch.log10(torch.clamp(sinr_eff.to(torch.float64).gather(1, last)[:, 0], min=1e-30))
    sinr_eff_last = torch.where(anyone, eff_db, float("nan"))
    tbler_sum = torch.where(sched, tbler.to(torch.float64), 0.0).sum(dim=1)
    # (the call's one way out: every tally, as float64 (the counts exact in it), in one read)
    per_ue = torch.stack([sched.sum(dim=1), prbs.sum(dim=1), (harq == 1).sum(dim=1), (harq == 0).sum(dim=1),
                          tbler_sum, mcs_last, sinr_eff_last], dim=1).to(torch.float64)  # [L, 7, cap]
    out = to_numpy(torch.cat([per_ue.flatten(), active.flatten(), torch.stack(delivered).flatten()]))
    tallies = out[:n_links * 7 * cap].reshape(n_links, 7, cap)[:, :, :n_ue]
    active_n = out[n_links * 7 * cap:n_links * 7 * cap + active.numel()].reshape(active.shape) != 0
    delivered_n = out[n_links * 7 * cap + active.numel():].reshape(n_links, n_slots, cap)[:, :, :n_ue]
    results = []
    for per, act, got in zip(tallies, active_n, delivered_n, strict=True):
        sched_n, prbs_n, acks_n, nacks_n = per[:4].astype(np.int64)
        tbler_n, mcs_n, eff_n = per[4:]
        with np.errstate(invalid="ignore", divide="ignore"):
            tbler_mean = np.where(sched_n > 0, tbler_n / sched_n, np.nan)
        results.append(SlotResults(got.sum(axis=0), sched_n, prbs_n, acks_n, nacks_n, mcs_n.astype(np.int64),
                                   tbler_mean, eff_n, act, got))
    return results
