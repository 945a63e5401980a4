"""A step of the downlink: what every UE receives of every cell (:func:`received`: power per
subband and wideband, RSRP, on the best SSB beam with beams), and the SINR
(:func:`downlink_sinr`) per slot and subband (what the link level decodes) and
wideband (what ``network.ue`` reports), with the co-channel cells as interference, either on
their sector patterns (:func:`~caviar_plugins.network.cells.sinr_db`) or, with SSB beams, on
the beams the other cells point at the UEs they schedule in each slot
(:func:`~caviar_plugins.network.beams.slot_sinr_db`)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from caviar_plugins.network.beams import slot_beams, slot_sinr_db, slot_sinrs_db
from caviar_plugins.network.cells import Cell, noise_dbm, rsrp_dbm, rx_power_dbm, sinr_db


def received(cells: Sequence[Cell], gains_db: np.ndarray, subband_prbs: np.ndarray, num_prb: int,
             beam_gains: np.ndarray | None = None):
    """What every UE receives of every cell from the channel's ``gains_db`` [ue, cell,
    subband] (dB): power [ue, cell, subband] and wideband (the subbands weighted by their
    PRBs) [ue, cell] in dBm, RSRP [ue, cell] and, with ``beam_gains`` [ue, cell, subband,
    beam] (linear), each cell's best beam [ue, cell] (None without), the wideband power and
    RSRP then the best beam's (L1-RSRP)."""
    rx = rx_power_dbm(cells, gains_db)
    weights = subband_prbs if gains_db.shape[-1] > 1 else np.ones(1)
    best = None
    if beam_gains is None:
        wideband = 10 * np.log10(np.average(10 ** (rx / 10), axis=-1, weights=weights))
    else:
        tx = np.array([c.tx_power_dbm for c in cells])[None, :]
        per_beam = 10 * np.log10(np.maximum(np.average(beam_gains, axis=2, weights=weights), 1e-40))
        wideband = tx + per_beam.max(axis=-1)
        best = per_beam.argmax(axis=-1)
    return rx, wideband, rsrp_dbm(cells, wideband, [num_prb] * len(cells)), best


def downlink_sinr(cells: Sequence[Cell], rx: np.ndarray, wideband: np.ndarray, serving: np.ndarray,
                  talking: np.ndarray | None, *, noise_figure_db: float, scheduled: bool,
                  beams: tuple[np.ndarray, np.ndarray] | None = None, slots: int = 1,
                  subband_prbs: np.ndarray | None = None, device: Any = "auto", linear: bool = False):
    """Per slot and subband [slot or 1, ue, subband], and wideband [ue], SINR and SIR (dB).
    ``linear``: with beams, the per-slot SINR as a ratio, a float64 tensor left on the torch
    ``device`` where it is computed (:func:`~caviar_plugins.network.ues.run_link` gives it to the
    link level there); without, the per-slot SINR is numpy's dB all the same (one row, small).
    ``rx``: received power [ue, cell, subband] and ``wideband`` [ue, cell] (dBm);
    ``serving`` [ue] (-1: none). With ``scheduled`` (``interference = "scheduled"``) only
    cells with data for someone (``talking`` [ue]; None: all) send. ``beams``: the beam gains
    [ue, cell, subband, beam] and each UE's best beam per cell [ue, cell]."""
    if beams is not None:
        return _beamformed(cells, beams, serving, talking, noise_figure_db, scheduled, slots, subband_prbs, device,
                           linear)
    load = None
    if scheduled:
        on = serving if talking is None else serving[talking]
        load = np.isin(np.arange(len(cells)), on).astype(float)
    sinr = sinr_db(cells, wideband, serving, noise_figure_db, load)
    sir = sinr_db(cells, wideband, serving, -np.inf, load)
    return sinr_db(cells, rx, serving, noise_figure_db, load)[None], sinr, sir


def _beamformed(cells: Sequence[Cell], beams: tuple[np.ndarray, np.ndarray], serving: np.ndarray,
                talking: np.ndarray | None, noise_figure_db: float, scheduled: bool, slots: int,
                subband_prbs: np.ndarray | None, device: Any, linear: bool = False):
    """With beams: per slot and subband, and wideband (the slots' mean); the other cells
    point at the UEs they schedule among ``talking`` (None: all)."""
    gains, best_beams = beams
    ue = np.arange(len(serving))
    best = np.where(serving >= 0, best_beams[ue, np.maximum(serving, 0)], 0)
    pointed = serving if talking is None else np.where(talking, serving, -1)
    chosen = slot_beams(pointed, best, len(cells), slots)
    bandwidth = np.array([c.bandwidth_hz for c in cells])[np.maximum(serving, 0)]
    noise = 10 ** (noise_dbm(bandwidth, noise_figure_db) / 10)
    per_slot = slot_sinr_db(cells, gains, serving, best, chosen, noise, scheduled, device, linear)
    weights = subband_prbs if gains.shape[2] > 1 and subband_prbs is not None else np.ones(gains.shape[2])
    flat = np.average(gains, axis=2, weights=weights)[:, :, None, :]
    # (the SINR and the SIR of the slots' wideband channel: one interference sum for both)
    sinr, sir = slot_sinrs_db(cells, flat, serving, best, chosen, (noise, np.zeros(len(serving))), scheduled, device)
    with np.errstate(divide="ignore"):  # (no signal: -inf, reported as None)
        sinr, sir = (10 * np.log10(np.mean(10 ** (x[:, :, 0] / 10), axis=0)) for x in (sinr, sir))
    return per_slot, sinr, sir
