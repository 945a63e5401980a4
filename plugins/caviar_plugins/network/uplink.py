"""The uplink (issue #41, part 2): PUSCH with open-loop power control.

Each UE sets its power with Sionna SYS's ``open_loop_uplink_power_control`` (TS 38.213
§7.1.1, no closed loop): ``P = min(P0 + α·PL + 10·log10(#PRB), P_max)`` dBm, ``PL`` the
pathloss the UE estimates from its serving cell's RSRP (so it includes the SSB beam or
array gain, as a real UE's estimate does). The serving cell receives ``P0 + (α − 1)·PL``
per PRB while the UE is below its limit.

Interference: in every slot each other cell schedules one of its UEs in turn (across the
band, as the downlink's beams do) and that UE's signal reaches the victim's cell through
the victim cell's receive beam toward its own UE (with ``beams``), or its element pattern
(without). Sionna SYS's link level then runs on the PUSCH MCS and BLER tables, with its own
outer-loop link adaptation.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from caviar_plugins.network.beams import scheduled_ues
from caviar_plugins.network.cells import Cell
from caviar_plugins.torch_device import HOST, compiled_once

ALPHAS = (0.0, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
"""TS 38.213's pathloss compensation factors (``msg3-Alpha``/``alpha``)."""


@dataclasses.dataclass(frozen=True)
class UplinkSettings:
    """``[modules.NAME.params.uplink]``: PUSCH power control and link level."""

    p0_dbm: float = -90.0
    """Target received power per PRB (TS 38.213's P0, -202..24 dBm)."""
    alpha: float = 0.8
    """Pathloss compensation (one of :data:`ALPHAS`)."""
    ue_max_power_dbm: float = 23.0
    """The UE's maximum power (P_CMAX; 23 dBm: power class 3)."""
    noise_figure_db: float = 5.0
    """The cell's receiver."""
    mcs_table: int = 1
    """NR PUSCH MCS table (1 or 2)."""

    def __post_init__(self):
        if isinstance(self.p0_dbm, bool) or not -202.0 <= self.p0_dbm <= 24.0:
            raise ValueError(f"p0_dbm: expected -202..24 dBm (TS 38.213's P0), got {self.p0_dbm!r}")
        if self.alpha not in ALPHAS:
            raise ValueError(f"alpha: expected one of {', '.join(f'{a:g}' for a in ALPHAS)} (TS 38.213), "
                             f"got {self.alpha!r}")
        if not -40.0 <= self.ue_max_power_dbm <= 33.0:
            raise ValueError(f"ue_max_power_dbm: expected -40..33 dBm, got {self.ue_max_power_dbm!r}")
        if self.mcs_table not in (1, 2):
            raise ValueError(f"mcs_table: expected an NR PUSCH MCS table index 1-2, got {self.mcs_table!r}")


def tx_power_dbm(s: UplinkSettings, pathloss_db: Any, num_prb: int, device: Any = "auto", keep: bool = False) -> Any:
    """[ue]: each UE's PUSCH power over ``num_prb`` PRBs, by Sionna SYS's open-loop power
    control (``pathloss_db`` [ue] from the serving cell's RSRP: numpy, or a tensor on the
    device), on the torch ``device`` of the link level (:mod:`caviar_plugins.torch_device`).
    ``keep``: a float64 tensor left there, not numpy."""
    import torch

    from caviar_plugins.torch_device import resolve, to_numpy, to_torch

    dbm = _power_dbm(to_torch(pathloss_db, resolve(device), torch.float64), s.alpha, s.p0_dbm, s.ue_max_power_dbm,
                     num_prb)
    return dbm if keep else to_numpy(dbm)


def _power_dbm(pathloss_db: Any, alpha: float, p0_dbm: float, max_dbm: float, num_prb: int) -> Any:
    """:func:`tx_power_dbm` of a float64 tensor [ue], on its device: a float64 tensor."""
    import torch
    from sionna.sys import open_loop_uplink_power_control

    pl = (10 ** (pathloss_db / 10)).to(torch.float32)
    subcarriers = torch.full(pl.shape, 12 * num_prb, dtype=torch.int32, device=pl.device)
    watts = open_loop_uplink_power_control(pl, subcarriers, alpha=alpha, p0_dbm=p0_dbm, ut_max_power_dbm=max_dbm)
    return 10 * torch.log10(watts.to(torch.float64)) + 30


GATHER_BYTES = 64 * 2**20
"""At most this much of the UEs' gains gathered at once for the uplink's interference
([slot, cell, cell, freq, beam] float64 each time): as many slots as fit, all of a step's at
21 cells (fewer operations a step), fewer with more cells."""


def slot_sinr_db(desired: Any, gains: Any, receive: np.ndarray, serving: np.ndarray,
                 carrier_of: np.ndarray, prb_power_dbm: Any, scheduled: np.ndarray, noise_prb_mw: float,
                 device: Any = HOST, linear: bool = False) -> Any:
    """[slot, ue, freq]: uplink SINR of every UE at its serving cell.

    ``desired`` [ue, freq]: gain from the UE to its cell (receive beam or array included);
    ``gains`` [ue', cell, freq, beam]: gain from UE ue' into each receive beam of each cell (one
    "beam", the element pattern, without beams); ``receive`` [ue]: the beam its serving cell
    receives the UE on; ``prb_power_dbm`` [ue]: power per PRB; ``scheduled`` [slot, cell]
    (:func:`~caviar_plugins.network.beams.scheduled_ues`); ``carrier_of`` [cell]. NaN for a UE
    without a cell. ``desired``, ``gains`` and ``prb_power_dbm``: numpy, or tensors on ``device``.
    Computed on the torch ``device`` (a setting or a ``torch.device``);
    ``linear``: the ratio itself, a float64 tensor left there (not its dB in numpy).

    What a victim hears depends on it only through its cell and receive beam: the interference
    is summed once per (cell, beam) and slot, over the UEs the other cells schedule, then read
    out per victim ([slot, cell, freq, beam], not a [victim, interferer] matrix)."""
    import torch

    from caviar_plugins.torch_device import resolve, to_numpy, to_torch

    dev = resolve(device)
    inputs = _interference_inputs(gains, receive, serving, carrier_of, scheduled, dev)
    ratio = _ratio(10 ** (to_torch(prb_power_dbm, dev, torch.float64) / 10), to_torch(desired, dev, torch.float64),
                   *inputs, noise_prb_mw)
    return ratio if linear else to_numpy(10 * torch.log10(ratio))  # (no path to its cell: -inf)


def _interference_inputs(gains: Any, receive: np.ndarray, serving: np.ndarray, carrier_of: np.ndarray,
                         scheduled: np.ndarray, dev: Any) -> tuple[Any, Any, Any, Any, Any, Any, int]:
    """:func:`slot_sinr_db`'s inputs beyond the powers and the desired gains, as tensors on
    ``dev``: the gains [ue', cell, freq, beam], each UE's cell and receive beam [ue], which cells
    hear which [cell, cell], the UE each cell schedules [slot, cell], the UEs without a cell
    [1, ue, 1], and the slots gathered at once (:data:`GATHER_BYTES`)."""
    import torch

    from caviar_plugins.torch_device import to_torch

    serving = np.asarray(serving)
    n_cell = scheduled.shape[1]
    # heard[k, c]: cell k hears cell c's UEs (the others on its carrier).
    heard = (carrier_of[None, :] == carrier_of[:, None]) & ~np.eye(n_cell, dtype=bool)
    g = to_torch(gains, dev, torch.float64)
    at_once = max(1, GATHER_BYTES // (8 * n_cell * math.prod(g.shape[1:])))  # (g[who] of that many slots: its bytes)
    return (g, to_torch(np.maximum(serving, 0), dev), to_torch(np.asarray(receive), dev),
            to_torch(heard, dev, torch.float64), to_torch(np.asarray(scheduled), dev, torch.int64),
            to_torch(serving < 0, dev)[None, :, None], at_once)


def _ratio(p: Any, desired: Any, g: Any, s: Any, rx: Any, heard: Any, heard_ues: Any, unserved: Any, at_once: int,
           noise_prb_mw: float) -> Any:
    """[slot, ue, freq]: :func:`slot_sinr_db`'s linear SINR, of tensors on one device: the UEs'
    power per PRB ``p`` (mW) [ue] and desired gains [ue, freq], then :func:`_interference_inputs`."""
    import torch

    signal = p[:, None] * desired  # [ue, freq]
    parts = []
    for a in range(0, heard_ues.shape[0], at_once):
        v = heard_ues[a:a + at_once]  # [slot, cell]: the UE each cell hears
        who = torch.clamp(v, min=0)
        weight = (v >= 0) * p[who]  # [slot, cell]
        per_beam = torch.einsum("sc,kc,sckfb->skbf", weight, heard, g[who])  # [slot, cell k, beam, freq]
        parts.append(per_beam[:, s, rx])  # [slot, ue, freq]
    ratio = signal[None] / (noise_prb_mw + torch.cat(parts))
    return torch.where(unserved, float("nan"), ratio)  # (a mask, not an indexing: no wait on a GPU)


def _power_and_ratio(pathloss_db: Any, desired: Any, g: Any, s: Any, rx: Any, heard: Any, heard_ues: Any,
                     unserved: Any, at_once: int, noise_prb_mw: float, alpha: float, p0_dbm: float, max_dbm: float,
                     num_prb: int) -> tuple[Any, Any, Any]:
    """The uplink's tensor work, one function (one compiled program with ``compile``): the UEs'
    powers (dBm [ue], :func:`tx_power_dbm`) from their pathlosses, then the per-slot linear SINR
    (:func:`_ratio`) with those powers per PRB, and those (mW [ue]). (Returned, the powers per PRB
    are computed once: otherwise inductor computes them again for every term of the interference
    sum, inside its loop, 3x slower on a CPU at 21 cells x 1,000 UEs, measured.)"""
    tx = _power_dbm(pathloss_db, alpha, p0_dbm, max_dbm, num_prb)
    p = 10 ** ((tx - 10 * math.log10(num_prb)) / 10)
    return tx, _ratio(p, desired, g, s, rx, heard, heard_ues, unserved, at_once, noise_prb_mw), p


power_and_ratio_compiled: Any = None
""":func:`_power_and_ratio` compiled (``torch.compile``, once a process, by
:func:`~caviar_plugins.torch_device.compiled_once`; the UE count a dynamic size after its first
change): on a GPU a few kernels instead of about 80 launches."""


def noise_per_prb_mw(subcarrier_spacing_hz: float, noise_figure_db: float) -> float:
    """k·T·B·NF over one PRB (12 subcarriers), mW."""
    return 1.380649e-23 * 290.0 * 12 * subcarrier_spacing_hz * 1e3 * 10 ** (noise_figure_db / 10)


def pathloss_db(tx_power_dbm: np.ndarray, rx_dbm: np.ndarray) -> np.ndarray:
    """The pathloss a UE estimates from its serving cell: transmitted minus received power."""
    return np.asarray(tx_power_dbm, dtype=float) - np.asarray(rx_dbm, dtype=float)


def uplink(cells: Sequence[Cell], s: UplinkSettings, serving: np.ndarray, rx_dbm: Any,
           beam_gains: Any, best_beams: np.ndarray | None, num_prb: int,
           subcarrier_spacing_hz: float, slots: int, device: str = "auto",
           talking: np.ndarray | None = None, linear: bool = False, compiled: bool = False) -> tuple[np.ndarray, Any]:
    """Every UE's PUSCH power (dBm, [ue]) and SINR ([slot, ue, freq]) from the downlink's
    measurements: ``rx_dbm`` [ue, cell, freq] the cells' received power (power, array gain
    and channel), and with SSB beams their gains [ue, cell, freq, beam] and each UE's best
    beam per cell [ue, cell]. The channel is reciprocal: the same gains both ways.
    ``talking`` [ue]: the UEs with data to send, the only ones other cells schedule (None: all).
    ``linear``: the SINR as a ratio, a float64 tensor on the torch ``device`` (:func:`slot_sinr_db`).
    ``compiled``: the powers and the SINR as one ``torch.compile`` program (the network's
    ``compile``): the same numbers to float32's rounding (the power control's), and on a GPU a few
    kernels, not about 80."""
    import torch

    from caviar_plugins.torch_device import to_numpy

    work = compiled_once(__name__, "power_and_ratio_compiled", _power_and_ratio) if compiled \
        else _power_and_ratio
    tx, ratio, _ = work(*uplink_args(cells, s, serving, rx_dbm, beam_gains, best_beams, num_prb,
                                     subcarrier_spacing_hz, slots, device, talking))
    return to_numpy(tx), ratio if linear else to_numpy(10 * torch.log10(ratio))


def uplink_args(cells: Sequence[Cell], s: UplinkSettings, serving: np.ndarray, rx_dbm: Any,
                beam_gains: Any, best_beams: np.ndarray | None, num_prb: int,
                subcarrier_spacing_hz: float, slots: int, device: str = "auto",
                talking: np.ndarray | None = None) -> tuple:
    """:func:`_power_and_ratio`'s arguments for :func:`uplink`'s (tensors on the torch device,
    then numbers): what a program that computes more at once takes
    (:func:`~caviar_plugins.network.sinrs.both_directions`)."""
    import torch

    from caviar_plugins.torch_device import resolve, to_torch

    n = len(serving)
    ue, sv = np.arange(n), np.maximum(np.asarray(serving), 0)
    power = np.array([c.tx_power_dbm for c in cells])
    array = np.array([c.array_gain_db for c in cells])
    dev = beam_gains.device if isinstance(beam_gains, torch.Tensor) else resolve(device)
    desired: Any
    pl: Any
    gains: Any
    if beam_gains is not None and best_beams is not None:  # (on the device, where the beam gains are)
        best = best_beams[ue, sv]
        gains = to_torch(beam_gains, dev, torch.float64)
        desired = gains[to_torch(ue, dev), to_torch(sv, dev), :, to_torch(best, dev)]  # [ue, freq]
        pl = -10 * torch.log10(torch.clamp(desired.mean(dim=-1), min=1e-40))
        receive = best  # (UE v into the beam cell k receives u on)
    else:
        rx_lin = np.mean(10 ** (np.asarray(rx_dbm) / 10), axis=-1)  # [ue, cell] (over the band)
        pl = pathloss_db(power[sv], 10 * np.log10(np.maximum(rx_lin[ue, sv], 1e-40)))
        channel = 10 ** ((np.asarray(rx_dbm) - (power + array)[None, :, None]) / 10)  # [ue, cell, freq]
        desired = channel[ue, sv] * 10 ** (array[sv] / 10)[:, None]
        gains, receive = channel[..., None], np.zeros(n, dtype=np.int64)  # element pattern only (the array serves u)
    scheduled = scheduled_ues(serving if talking is None else np.where(talking, serving, -1), len(cells), slots)
    carriers = np.array([c.carrier_hz for c in cells])
    return (to_torch(pl, dev, torch.float64), to_torch(desired, dev, torch.float64),
            *_interference_inputs(gains, receive, serving, carriers, scheduled, dev),
            noise_per_prb_mw(subcarrier_spacing_hz, s.noise_figure_db), s.alpha, s.p0_dbm, s.ue_max_power_dbm, num_prb)


def mean_sinr_db(per_slot: Any) -> np.ndarray:
    """[ue]: the SINR over a step's slots and subbands (their linear mean, in dB) of the
    per-slot linear SINRs [slot, ue, freq] (a tensor, :func:`uplink`'s ``linear``; NaN for a
    UE without a cell, -inf for one without a path), averaged where they are."""
    from caviar_plugins.torch_device import to_numpy

    return to_numpy(_mean_db(per_slot))


def _mean_db(per_slot: Any) -> Any:
    """:func:`mean_sinr_db`'s tensor work: [ue] of the per-slot linear SINRs [slot, ue, freq]."""
    import torch

    return 10 * torch.log10(per_slot.mean(dim=(0, 2)))
