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

from caviar_plugins.network.beams import sinr_and_wideband_args, slot_beams, slot_sinr_and_wideband
from caviar_plugins.network.cells import Cell, noise_dbm, rsrp_dbm, rx_power_dbm, sinr_db
from caviar_plugins.torch_device import HOST, resolve, to_numpy, to_torch


def received(cells: Sequence[Cell], gains_db: Any, subband_prbs: np.ndarray, num_prb: int,
             beam_gains: Any = None):
    """What every UE receives of every cell from the channel's ``gains_db`` [ue, cell,
    subband] (dB): power [ue, cell, subband] and wideband (the subbands weighted by their
    PRBs) [ue, cell] in dBm, RSRP [ue, cell] and, with ``beam_gains`` [ue, cell, subband,
    beam] (linear), each cell's best beam [ue, cell] (None without), the wideband power and
    RSRP then the best beam's (L1-RSRP). ``gains_db`` and ``beam_gains`` are numpy, or tensors
    on the network's torch device (the ray-traced channel's): with beams the per-beam sums are
    made there and only the wideband power and best beams [ue, cell] are read to the host, once;
    the power per subband then stays there too (no step reads it with beams)."""
    weights = subband_prbs if gains_db.shape[-1] > 1 else np.ones(1)
    if beam_gains is None:
        rx = rx_power_dbm(cells, gains_db if isinstance(gains_db, np.ndarray) else to_numpy(gains_db))
        wideband = 10 * np.log10(np.average(10 ** (rx / 10), axis=-1, weights=weights))
        return rx, wideband, rsrp_dbm(cells, wideband, [num_prb] * len(cells)), None
    import torch

    g = beam_gains if isinstance(beam_gains, torch.Tensor) else to_torch(beam_gains, HOST, torch.float64)
    dev = g.device
    tx = np.array([c.tx_power_dbm for c in cells])
    rx = rx_power_dbm(cells, gains_db) if isinstance(gains_db, np.ndarray) else \
        to_torch(tx + np.array([c.array_gain_db for c in cells]), dev, torch.float64)[None, :, None] + gains_db
    w = to_torch(np.asarray(weights, dtype=float), dev, torch.float64)
    per_beam = 10 * torch.log10(torch.clamp((g * w[:, None]).sum(dim=2) / w.sum(), min=1e-40))  # [ue, cell, beam]
    best_t = torch.argmax(per_beam, dim=-1)
    strongest = per_beam.gather(-1, best_t[..., None])[..., 0]
    read = to_numpy(torch.stack([strongest, best_t.to(torch.float64)]))  # (the host's one read)
    wideband, best = tx[None, :] + read[0], read[1].astype(np.int64)
    return rx, wideband, rsrp_dbm(cells, wideband, [num_prb] * len(cells)), best


def downlink_sinr(cells: Sequence[Cell], rx: np.ndarray, wideband: np.ndarray, serving: np.ndarray,
                  talking: np.ndarray | None, *, noise_figure_db: float, scheduled: bool,
                  beams: tuple[Any, np.ndarray] | None = None, slots: int = 1,
                  subband_prbs: np.ndarray | None = None, device: Any = "auto", linear: bool = False,
                  compiled: bool = False):
    """Per slot and subband [slot or 1, ue, subband], and wideband [ue], SINR and SIR (dB).
    ``linear``: with beams, the per-slot SINR as a ratio, a float64 tensor left on the torch
    ``device`` where it is computed (:func:`~caviar_plugins.network.ues.run_links` gives it to the
    link level there); without, the per-slot SINR is numpy's dB all the same (one row, small).
    ``rx``: received power [ue, cell, subband] and ``wideband`` [ue, cell] (dBm);
    ``serving`` [ue] (-1: none). With ``scheduled`` (``interference = "scheduled"``) only
    cells with data for someone (``talking`` [ue]; None: all) send. ``beams``: the beam gains
    [ue, cell, subband, beam] and each UE's best beam per cell [ue, cell]; ``compiled``: with
    them, the tensor work as one ``torch.compile`` program (the network's ``compile``)."""
    if beams is not None:
        return _beamformed(cells, beams, serving, talking, noise_figure_db, scheduled, slots, subband_prbs, device,
                           linear, compiled)
    load = None
    if scheduled:
        on = serving if talking is None else serving[talking]
        load = np.isin(np.arange(len(cells)), on).astype(float)
    sinr = sinr_db(cells, wideband, serving, noise_figure_db, load)
    sir = sinr_db(cells, wideband, serving, -np.inf, load)
    return sinr_db(cells, rx, serving, noise_figure_db, load)[None], sinr, sir


def _beamformed(cells: Sequence[Cell], beams: tuple[Any, np.ndarray], serving: np.ndarray,
                talking: np.ndarray | None, noise_figure_db: float, scheduled: bool, slots: int,
                subband_prbs: np.ndarray | None, device: Any, linear: bool = False, compiled: bool = False):
    """With beams: per slot and subband, and wideband (the slots' mean); the other cells
    point at the UEs they schedule among ``talking`` (None: all)."""
    # (per slot and subband; and the SINR and the SIR of the subbands' weighted mean channel, their
    # ratios averaged over the slots: one interference sum for all, read to the host once)
    return slot_sinr_and_wideband(*_beamformed_inputs(cells, beams, serving, talking, noise_figure_db, scheduled,
                                                      slots, subband_prbs, device), linear, compiled)


def beamformed_args(cells: Sequence[Cell], serving: np.ndarray, talking: np.ndarray | None, *,
                    noise_figure_db: float, scheduled: bool, beams: tuple[Any, np.ndarray], slots: int = 1,
                    subband_prbs: np.ndarray | None = None, device: Any = "auto", linear: bool = False) -> tuple:
    """:func:`downlink_sinr`'s tensor work with ``beams`` (its arguments by the same names) as
    the arguments of its program (:func:`~caviar_plugins.network.beams.sinr_and_wideband_args`):
    for a program that computes more at once (:func:`~caviar_plugins.network.sinrs.both_directions`)."""
    return sinr_and_wideband_args(*_beamformed_inputs(cells, beams, serving, talking, noise_figure_db, scheduled,
                                                      slots, subband_prbs, device), linear)


def _beamformed_inputs(cells: Sequence[Cell], beams: tuple[Any, np.ndarray], serving: np.ndarray,
                       talking: np.ndarray | None, noise_figure_db: float, scheduled: bool, slots: int,
                       subband_prbs: np.ndarray | None,
                       device: Any) -> tuple[Sequence[Cell], Any, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool,
                                             np.ndarray, Any]:
    """:func:`~caviar_plugins.network.beams.slot_sinr_and_wideband`'s inputs with beams, up to
    its device: the beams each cell points at in each slot, the noise and the subbands' weights."""
    import torch

    gains, best_beams = beams
    dev = gains.device if isinstance(gains, torch.Tensor) else resolve(device)
    ue = np.arange(len(serving))
    best = np.where(serving >= 0, best_beams[ue, np.maximum(serving, 0)], 0)
    pointed = serving if talking is None else np.where(talking, serving, -1)
    chosen = slot_beams(pointed, best, len(cells), slots)
    bandwidth = np.array([c.bandwidth_hz for c in cells])[np.maximum(serving, 0)]
    noise = 10 ** (noise_dbm(bandwidth, noise_figure_db) / 10)
    n_f = gains.shape[2]
    weights = subband_prbs if n_f > 1 and subband_prbs is not None else np.ones(n_f)
    return cells, gains, serving, best, chosen, noise, scheduled, weights, dev
