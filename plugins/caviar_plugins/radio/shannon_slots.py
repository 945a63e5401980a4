"""The Shannon link model of a link level's call (:class:`~caviar_plugins.radio.link_level.LinkLevel`
with ``link_model = "shannon"``): equal time shares at the Shannon rate, in numpy (no Sionna SYS)."""

from __future__ import annotations

import numpy as np

from caviar_plugins.radio.link_queue import CallQueue
from caviar_plugins.radio.link_settings import LinkSettings
from caviar_plugins.radio.slot_results import SlotResults


def shannon_slots(settings: LinkSettings, n_cell: int, sinr_db: np.ndarray, serving: np.ndarray,
                  queue: CallQueue) -> SlotResults:
    """A call's slots by the Shannon link model (``link_model = "shannon"``): each cell's time shared
    equally among its UEs (with queues, slot by slot among those with bits), each getting
    ``Σ_subbands B_k·log2(1 + SINR_k)`` in its share. ``sinr_db`` [n_slots, n_ue, subbands] (NaN:
    no cell), ``serving`` [n_ue] (-1: none)."""
    n_slots, n_ue, _ = sinr_db.shape
    band = settings.subband_prbs * settings.prb_bandwidth_hz  # [subbands]
    se = np.log2(1 + 10 ** (np.nan_to_num(sinr_db, nan=-np.inf) / 10))
    rate = (se * band).sum(axis=2) * settings.slot_s  # [slot, ue] bits with the whole cell
    active = np.zeros((n_slots, n_cell), dtype=bool)
    sched = np.zeros(n_ue)
    if not queue.finite:  # a full buffer: every slot alike, one share for all (no slot loop)
        counts, share = _time_shares(n_cell, serving >= 0, serving)
        queue.delivered[:] = rate * share
        active[:, counts > 0] = True
        sched += np.where(serving >= 0, n_slots, 0)
    else:  # queues: slot by slot, among the UEs with bits
        for k in range(n_slots):
            eligible = (serving >= 0) & queue.eligible(k)
            counts, share = _time_shares(n_cell, eligible, serving)
            queue.take(k, rate[k] * share)
            active[k, counts > 0] = True
            sched += eligible
    zeros = np.zeros(n_ue, dtype=int)
    known = ~np.isnan(sinr_db)
    count = known.sum(axis=(0, 2))  # (a UE without a cell has no SINR: NaN, without a warning)
    mean = np.where(count > 0, np.where(known, sinr_db, 0.0).sum(axis=(0, 2)) / np.maximum(count, 1), np.nan)
    return SlotResults(queue.delivered.sum(axis=0), sched.astype(int), zeros, zeros, zeros,
                       np.full(n_ue, -1), np.full(n_ue, np.nan), mean, active, queue.delivered)


def _time_shares(n_cell: int, eligible: np.ndarray, serving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shannon's equal time shares: the UEs each cell serves among ``eligible`` [n_cell],
    and each UE's share of its cell's time [n_ue] (0: not eligible)."""
    counts = np.bincount(serving[eligible], minlength=n_cell)
    return counts, np.where(eligible, 1.0 / np.maximum(counts[np.maximum(serving, 0)], 1), 0.0)
