"""The step's SINRs before the link level (:func:`step_sinrs`): the downlink's, per slot and
wideband (:func:`~caviar_plugins.network.downlink.downlink_sinr`), and with the uplink its
powers and SINR (:func:`~caviar_plugins.network.uplink.uplink`); with beams and the uplink,
both directions' tensor work as one program (:func:`both_directions`)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from caviar_plugins.network.beams import _sinr_and_wideband
from caviar_plugins.network.cells import Cell
from caviar_plugins.network.downlink import beamformed_args, downlink_sinr
from caviar_plugins.network.uplink import _mean_db, _power_and_ratio, mean_sinr_db, uplink, uplink_args
from caviar_plugins.torch_device import compiled_once


def step_sinrs(p: Any, cells: Sequence[Cell], rx: Any, wideband: np.ndarray, serving: np.ndarray,
               talking: np.ndarray | None, ul_talking: np.ndarray | None, beams: tuple[Any, np.ndarray] | None,
               slots: int, subband_prbs: np.ndarray, device: Any) -> tuple:
    """The step's downlink SINR (per slot, as the link level takes it; wideband SINR and SIR
    [ue], dB) and, with the uplink (``p.uplink``, the network's settings ``p``), the UEs' powers
    (dBm), per-slot SINR and mean SINR (dB) [ue] (else None). ``talking`` and ``ul_talking``: the
    UEs with data in each direction (None: all); ``beams``: the beam gains and best beams."""
    dl = dict(noise_figure_db=p.noise_figure_db, scheduled=p.interference == "scheduled", beams=beams,
              slots=slots, subband_prbs=subband_prbs, device=device, linear=True)
    if p.uplink is None:
        return (*downlink_sinr(cells, rx, wideband, serving, talking, **dl, compiled=p.compile), None)
    beam_gains, best = beams if beams is not None else (None, None)
    ul = (cells, p.uplink, serving, rx, beam_gains, best, p.num_prb, p.subcarrier_spacing_hz, slots, device, ul_talking)
    if beams is None:
        dl_slot, sinr, sir = downlink_sinr(cells, rx, wideband, serving, talking, **dl, compiled=p.compile)
        tx, ul_slot = uplink(*ul, linear=True, compiled=p.compile)
        ul_sinr = mean_sinr_db(ul_slot)
    else:
        dl_slot, sinr, sir, tx, ul_slot, ul_sinr = both_directions(
            beamformed_args(cells, serving, talking, **dl), uplink_args(*ul), p.compile)
    return dl_slot, sinr, sir, (tx, ul_slot, ul_sinr)


def both_directions(downlink: tuple, uplink: tuple, compiled: bool = False) -> tuple:
    """The downlink's SINRs (:func:`~caviar_plugins.network.beams.slot_sinr_and_wideband`'s, with
    beams, of :func:`~caviar_plugins.network.downlink.beamformed_args`' ``downlink``) and the
    uplink's powers and SINR (:func:`~caviar_plugins.network.uplink.uplink`'s, of
    :func:`~caviar_plugins.network.uplink.uplink_args`' ``uplink``) from one
    program: with ``compiled`` one ``torch.compile`` call a step instead of two (each costs the host
    its entry, about 0.2-0.4 ms on a 2-core CPU) and one read to the host instead of three. Returns
    the downlink's per-slot SINR (a tensor), its wideband SINR and SIR [ue] (dB), the uplink's
    powers [ue] (dBm), its per-slot SINR (a tensor) and its mean SINR [ue]
    (:func:`~caviar_plugins.network.uplink.mean_sinr_db`): the same numbers as the two apart."""
    from caviar_plugins.torch_device import to_numpy

    work = compiled_once(__name__, "both_directions_compiled", _both_directions) if compiled else _both_directions
    dl_per_slot, ul_per_slot, read, _ = work(downlink, uplink)
    read = to_numpy(read)  # (the host's one read: [4, ue])
    return dl_per_slot, read[0], read[1], read[2], ul_per_slot, read[3]


def _both_directions(downlink: tuple, uplink: tuple) -> tuple[Any, Any, Any, Any]:
    """:func:`both_directions`' tensor work: the per-slot SINRs of both directions, the
    downlink's wideband SINR and SIR, the uplink's powers and mean SINR as one tensor [4, ue],
    and the uplink's powers per PRB (returned for inductor to realise them once: see
    :func:`~caviar_plugins.network.uplink.uplink`)."""
    import torch

    dl_per_slot, wide = _sinr_and_wideband(*downlink)
    tx, ul_per_slot, p = _power_and_ratio(*uplink)
    return dl_per_slot, ul_per_slot, torch.cat([wide, tx[None], _mean_db(ul_per_slot)[None]]), p


both_directions_compiled: Any = None
""":func:`_both_directions` compiled (``torch.compile``, once a process, by
:func:`~caviar_plugins.torch_device.compiled_once`)."""
