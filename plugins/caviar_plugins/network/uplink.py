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
from caviar_plugins.torch_device import HOST

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
    from sionna.sys import open_loop_uplink_power_control

    from caviar_plugins.torch_device import resolve, to_numpy, to_torch

    where = resolve(device)
    pl = (10 ** (to_torch(pathloss_db, where, torch.float64) / 10)).to(torch.float32)
    subcarriers = torch.full(pl.shape, 12 * num_prb, dtype=torch.int32, device=where)
    watts = open_loop_uplink_power_control(pl, subcarriers, alpha=s.alpha, p0_dbm=s.p0_dbm,
                                           ut_max_power_dbm=s.ue_max_power_dbm)
    dbm = 10 * torch.log10(watts.to(torch.float64)) + 30
    return dbm if keep else to_numpy(dbm)


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
    serving = np.asarray(serving)
    n_slot, n_cell = scheduled.shape
    # heard[k, c]: cell k hears cell c's UEs (the others on its carrier).
    heard = (carrier_of[None, :] == carrier_of[:, None]) & ~np.eye(n_cell, dtype=bool)
    p = 10 ** (to_torch(prb_power_dbm, dev, torch.float64) / 10)
    g, heard_t = to_torch(gains, dev, torch.float64), to_torch(heard, dev, torch.float64)
    s, rx = to_torch(np.maximum(serving, 0), dev), to_torch(np.asarray(receive), dev)
    signal = p[:, None] * to_torch(desired, dev, torch.float64)  # [ue, freq]
    parts, heard_ues = [], to_torch(np.asarray(scheduled), dev, torch.int64)  # [slot, cell]: the UE each cell hears
    at_once = max(1, GATHER_BYTES // (8 * n_cell * math.prod(g.shape[1:])))  # (g[who] of that many slots: its bytes)
    for a in range(0, n_slot, at_once):
        v = heard_ues[a:a + at_once]
        who = torch.clamp(v, min=0)
        weight = (v >= 0) * p[who]  # [slot, cell]
        per_beam = torch.einsum("sc,kc,sckfb->skbf", weight, heard_t, g[who])  # [slot, cell k, beam, freq]
        parts.append(per_beam[:, s, rx])  # [slot, ue, freq]
    ratio = signal[None] / (noise_prb_mw + torch.cat(parts))
    unserved = to_torch(serving < 0, dev)[None, :, None]
    if linear:
        return torch.where(unserved, float("nan"), ratio)
    out = 10 * torch.log10(ratio)  # (no path to its cell: -inf)
    return to_numpy(torch.where(unserved, float("nan"), out))  # (a mask, not an indexing: no wait on a GPU)


def noise_per_prb_mw(subcarrier_spacing_hz: float, noise_figure_db: float) -> float:
    """k·T·B·NF over one PRB (12 subcarriers), mW."""
    return 1.380649e-23 * 290.0 * 12 * subcarrier_spacing_hz * 1e3 * 10 ** (noise_figure_db / 10)


def pathloss_db(tx_power_dbm: np.ndarray, rx_dbm: np.ndarray) -> np.ndarray:
    """The pathloss a UE estimates from its serving cell: transmitted minus received power."""
    return np.asarray(tx_power_dbm, dtype=float) - np.asarray(rx_dbm, dtype=float)


def uplink(cells: Sequence[Cell], s: UplinkSettings, serving: np.ndarray, rx_dbm: Any,
           beam_gains: Any, best_beams: np.ndarray | None, num_prb: int,
           subcarrier_spacing_hz: float, slots: int, device: str = "auto",
           talking: np.ndarray | None = None, linear: bool = False) -> tuple[np.ndarray, Any]:
    """Every UE's PUSCH power (dBm, [ue]) and SINR ([slot, ue, freq]) from the downlink's
    measurements: ``rx_dbm`` [ue, cell, freq] the cells' received power (power, array gain
    and channel), and with SSB beams their gains [ue, cell, freq, beam] and each UE's best
    beam per cell [ue, cell]. The channel is reciprocal: the same gains both ways.
    ``talking`` [ue]: the UEs with data to send, the only ones other cells schedule (None: all).
    ``linear``: the SINR as a ratio, a float64 tensor on the torch ``device`` (:func:`slot_sinr_db`)."""
    import torch

    from caviar_plugins.torch_device import resolve, to_numpy, to_torch

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
    tx = tx_power_dbm(s, pl, num_prb, dev, keep=True)
    scheduled = scheduled_ues(serving if talking is None else np.where(talking, serving, -1), len(cells), slots)
    carriers = np.array([c.carrier_hz for c in cells])
    sinr = slot_sinr_db(desired, gains, receive, serving, carriers, tx - 10 * np.log10(num_prb), scheduled,
                        noise_per_prb_mw(subcarrier_spacing_hz, s.noise_figure_db), dev, linear)
    return to_numpy(tx), sinr


def mean_sinr_db(per_slot: Any) -> np.ndarray:
    """[ue]: the SINR over a step's slots and subbands (their linear mean, in dB) of the
    per-slot linear SINRs [slot, ue, freq] (a tensor, :func:`uplink`'s ``linear``; NaN for a
    UE without a cell, -inf for one without a path), averaged where they are."""
    import torch

    from caviar_plugins.torch_device import to_numpy

    return to_numpy(10 * torch.log10(per_slot.mean(dim=(0, 2))))
