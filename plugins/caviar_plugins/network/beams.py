"""SSB beams from the channel (issue #41, part 1, the computation): a DFT codebook on each
cell's panel, the gain of every beam toward every UE from the channel's paths, and the
SINR when each interfering cell points the beam it scheduled.

Geometry. A cell's panel is a uniform planar array of ``rows × cols`` elements at half a
wavelength, facing its azimuth (counter-clockwise from +x), tilted down by its downtilt.
In the panel's frame (x' the boresight, y' along the rows, z' up the columns) a departure
direction has the spatial frequencies ``u = sin θ' sin φ'`` (horizontal) and
``v = cos θ'`` (vertical); element (m, n) sees the phase ``π (n u + m v)``. The panel's frame
is the scene's rotated by ``Rz(azimuth)·Ry(downtilt)`` (TR 38.901 §7.1.3, no slant), exactly:
the element pattern takes its angles ``θ', φ'`` from the same rotation
(:func:`~caviar_plugins.network.cells.local_angles_deg`), and a beam's reported direction is
its (u, v) rotated back (:func:`scene_direction`).

Codebook. ``beams_h × beams_v`` DFT beams, ``beams_h ≤ cols`` and ``beams_v ≤ rows`` (a
codebook larger than the array has no more orthogonal beams): beam (i, k) steers to
``u_i = (2i + 1)/beams_h − 1`` and ``v_k = (2k + 1)/beams_v − 1``, unit-norm weights: for an
even N (beams along an axis) the textbook DFT grid ``u = 2i/N`` (wrapped into [−1, 1)) moved
by half a bin, 1/N (for an odd N both grids are the same beams). The textbook grid has a beam
on boresight and one at ``u = −1``, whose phases at half a wavelength are those of ``u = +1``:
it points along the panel's plane both ways (φ' = ±90°, where the element pattern is 23 dB
down) and is lost. Moved half a bin, the N beams sit symmetrically about boresight (±1/N,
±3/N, …, ±(N−1)/N), all inside the visible region, still 2/N apart (orthogonal when N divides
the elements along that axis). The price: boresight falls midway between the beams at ±1/N,
at their crossover, 3.87 dB below the peak for 8 beams on 8 columns and 3.70 dB for 4 on 4
(the Dirichlet kernel half a bin off, ``1/(N sin(π/2N))²``). One beam (``vertical = 1``)
points along the panel's boresight, the mechanical tilt. Fewer beams than elements leave
holes: the beams are as narrow as the panel (first nulls 2/elements away) but 2/N apart, so
with 4 beams on 8 columns boresight lies in a null of every beam.

Beam gain of beam ``w`` toward a UE with paths ``a_p`` (complex amplitude, the element
pattern applied) leaving along ``k_p``: ``|Σ_p a_p · e(k_p)ᵀ w|²``, where ``e`` has unit-modulus
entries, so a beam aimed exactly along a single path gains ``rows · cols``.

In the ``radio-network`` plugin (``beams = { horizontal = 8 }``): each cell sweeps its
codebook, a UE's L1-RSRP of a cell is its best beam's (cell selection and A3 handover use
it), data goes out on the serving cell's best beam for the UE, and in every slot each other
cell on the carrier interferes with the beam toward the UE it schedules then
(:func:`slot_beams`: its UEs in turn, one per slot), evaluated on the victim's channel.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from caviar_plugins.constants import SPEED_OF_LIGHT
from caviar_plugins.network.cells import Cell, pattern_gain_db
from caviar_plugins.torch_device import HOST, compiled_once, one_blas_thread, resolve, to_numpy, to_torch


@dataclasses.dataclass(frozen=True)
class BeamSettings:
    """``[modules.NAME.params.beams]``: the SSB codebook of every cell's panel."""

    horizontal: int = 8
    """DFT beams across the panel (at most its columns)."""
    vertical: int = 1
    """DFT beams up the panel (at most its rows)."""

    def __post_init__(self):
        for key in ("horizontal", "vertical"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{key}: expected a number of beams >= 1, got {value!r}")

    def codebook(self, array: tuple[int, int]) -> Codebook:
        return Codebook(rows=array[0], cols=array[1], beams_h=self.horizontal, beams_v=self.vertical)


@dataclasses.dataclass(frozen=True)
class Codebook:
    """DFT beams on a ``rows × cols`` panel: ``beams_h`` across, ``beams_v`` up."""

    rows: int
    cols: int
    beams_h: int
    beams_v: int = 1

    def __post_init__(self):
        if not 1 <= self.beams_h <= self.cols:
            raise ValueError(f"beams: {self.beams_h} horizontal beams on {self.cols} columns; expected 1..{self.cols} "
                             "(a DFT codebook has at most one orthogonal beam per element)")
        if not 1 <= self.beams_v <= self.rows:
            raise ValueError(f"beams: {self.beams_v} vertical beams on {self.rows} rows; expected 1..{self.rows}")

    @property
    def size(self) -> int:
        return self.beams_h * self.beams_v

    def pointing(self) -> np.ndarray:
        """[beam, 2]: each beam's (u, v), horizontal index fastest."""
        u = (2 * np.arange(self.beams_h) + 1) / self.beams_h - 1
        v = (2 * np.arange(self.beams_v) + 1) / self.beams_v - 1
        return np.stack(np.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)

    def weights(self) -> np.ndarray:
        """[beam, rows·cols] unit-norm weights."""
        p = self.pointing()
        return steering(self.rows, self.cols, p[:, 0], p[:, 1]).conj() / math.sqrt(self.rows * self.cols)


def steering(rows: int, cols: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[..., rows·cols] the panel's response at spatial frequencies (u, v), unit-modulus."""
    m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    phase = np.pi * (np.asarray(u)[..., None] * n.reshape(-1) + np.asarray(v)[..., None] * m.reshape(-1))
    return np.exp(1j * phase)


def panel_frequencies(cell: Cell, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of unit ``direction`` vectors [..., 3] (scene frame) in ``cell``'s panel frame."""
    a, t = math.radians(cell.azimuth_deg), math.radians(cell.downtilt_deg)
    d = np.asarray(direction, dtype=float)
    # Undo the azimuth (about z), then the downtilt (about the panel's y axis).
    x = math.cos(a) * d[..., 0] + math.sin(a) * d[..., 1]
    y = -math.sin(a) * d[..., 0] + math.cos(a) * d[..., 1]
    # The boresight (cos t, 0, -sin t) maps to the panel's x axis: z' = sin t · x + cos t · z.
    up = math.sin(t) * x + math.cos(t) * d[..., 2]
    return y, up  # sin θ' sin φ' = y', cos θ' = z'


def beam_gains(cell: Cell, codebook: Codebook, amplitude: np.ndarray, departure: np.ndarray) -> np.ndarray:
    """[ue, beam]: ``|Σ_p a_p e(k_p)ᵀ w_b|²`` for paths ``amplitude`` [ue, path] (complex, the
    element pattern applied; 0 for no path) leaving the cell along ``departure`` [ue, path, 3]."""
    u, v = panel_frequencies(cell, departure)
    e = steering(codebook.rows, codebook.cols, u, v)  # [ue, path, element]
    h = np.einsum("up,upe->ue", np.asarray(amplitude), e)  # the UE's channel across the panel
    return np.abs(h @ codebook.weights().T) ** 2


def line_of_sight(cells: Sequence[Cell], ues: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Free space, one path per cell and UE: amplitudes [ue, cell, 1] (Friis and the sector
    pattern, real) and departure directions [ue, cell, 1, 3]."""
    ues = np.asarray(ues, dtype=float)
    amplitude = np.zeros((len(ues), len(cells), 1), dtype=complex)
    departure = np.zeros((len(ues), len(cells), 1, 3))
    for c, cell in enumerate(cells):
        d = ues - np.asarray(cell.position)
        dist = np.linalg.norm(d, axis=-1)
        k = d / dist[:, None]
        theta = np.degrees(np.arccos(np.clip(k[:, 2], -1, 1)))
        phi = np.degrees(np.arctan2(k[:, 1], k[:, 0]))
        lam = SPEED_OF_LIGHT / cell.carrier_hz
        amplitude[:, c, 0] = lam / (4 * np.pi * dist) * 10 ** (pattern_gain_db(cell, theta, phi) / 20)
        departure[:, c, 0] = k
    return amplitude, departure


def beamformed_sinr_db(cells: Sequence[Cell], gains: np.ndarray, serving: np.ndarray, beam: np.ndarray,
                       scheduled_beam: np.ndarray, noise_mw: float) -> np.ndarray:
    """[ue]: SINR of each UE on its serving cell's beam ``beam[u]``, every other cell ``c`` on
    the carrier transmitting its beam ``scheduled_beam[c]`` (-1: silent), both evaluated on
    the victim's channel. ``gains`` [ue, cell, beam] linear beam gains (:func:`beam_gains`)."""
    power = 10 ** (np.array([c.tx_power_dbm for c in cells]) / 10)
    carrier = np.array([c.carrier_hz for c in cells])
    out = np.full(len(serving), np.nan)
    for u, s in enumerate(np.asarray(serving)):
        if s < 0:
            continue
        interference = sum(power[c] * gains[u, c, scheduled_beam[c]] for c in range(len(cells))
                           if c != s and carrier[c] == carrier[s] and scheduled_beam[c] >= 0)
        out[u] = 10 * math.log10(power[s] * gains[u, s, beam[u]] / (noise_mw + interference))
    return out


def all_beam_gains(cells: Sequence[Cell], codebooks: Sequence[Codebook], amplitude: np.ndarray,
                   departure: np.ndarray) -> np.ndarray:
    """[ue, cell, freq, beam]: :func:`beam_gains` of every cell, for path amplitudes
    [ue, cell, path, freq] (per frequency) leaving along ``departure`` [ue, cell, path, 3]."""
    return gains_of_responses(amplitude, beam_responses(cells, codebooks, departure))


def beam_responses(cells: Sequence[Cell], codebooks: Sequence[Codebook], departure: np.ndarray,
                   device: Any = HOST) -> Any:
    """[ue, cell, path, beam]: each path's response to each beam of its cell's codebook,
    ``e(k_p)ᵀ w_b`` for paths leaving along ``departure`` [ue, cell, path, 3] (0 past a
    smaller codebook's beams), a complex128 tensor on the torch ``device``. It changes only
    where the paths are traced again, so a caller keeps it there from one trace to the next
    (:func:`gains_of_responses` per step)."""
    import torch

    width = max(cb.size for cb in codebooks)
    out = np.zeros((*departure.shape[:3], width), dtype=complex)
    with one_blas_thread():  # (numpy's BLAS threads would spin on the cores torch needs next)
        for c, (cell, cb) in enumerate(zip(cells, codebooks, strict=True)):
            u, v = panel_frequencies(cell, departure[:, c])
            out[:, c, :, :cb.size] = steering(cb.rows, cb.cols, u, v) @ cb.weights().T
    return to_torch(out, resolve(device), torch.complex128)


def gains_of_responses(amplitude: Any, responses: Any, rows: np.ndarray | None = None, keep: bool = False) -> Any:
    """[ue, cell, freq, beam]: ``|Σ_p a_p e(k_p)ᵀ w_b|²`` for path amplitudes [ue, cell, path,
    freq] (numpy or a tensor) and the paths' :func:`beam_responses` (of the UEs ``rows`` of
    them, None: all): one batched product, on the responses' device. ``keep``: the float64
    tensor left there (what the network's step reads there), not numpy."""
    import torch

    dev = responses.device
    r = responses if rows is None else responses[to_torch(rows, dev)]
    a = to_torch(amplitude, dev, torch.complex128)
    gains = torch.abs(torch.matmul(a.transpose(2, 3), r)) ** 2
    return gains if keep else to_numpy(gains)


_LAST_SCHEDULED: list = [None, None]  # (the last call's serving cells, cells and slots; its result)


def scheduled_ues(serving: np.ndarray, n_cells: int, slots: int) -> np.ndarray:
    """[slot, cell]: the UE (index) each cell schedules in each slot, its UEs in turn (UE
    order), one per slot; -1 for a cell that serves nobody. Array work: the UEs sorted by
    cell (stably, so in UE order within one), each cell's turn an offset into its run.
    The same arguments as the last call's (a step's downlink and uplink with full buffers ask
    for the same): a copy of its result."""
    serving = np.asarray(serving)
    key = (serving.dtype.str, serving.tobytes(), n_cells, slots)
    if _LAST_SCHEDULED[0] != key:
        _LAST_SCHEDULED[:] = key, _scheduled_ues(serving, n_cells, slots)
    return _LAST_SCHEDULED[1].copy()


def _scheduled_ues(serving: np.ndarray, n_cells: int, slots: int) -> np.ndarray:
    on = np.flatnonzero(serving >= 0)
    order = on[np.argsort(serving[on], kind="stable")]  # the served UEs, cell by cell, in UE order
    counts = np.bincount(serving[on], minlength=n_cells)[:n_cells]
    starts = np.cumsum(counts) - counts
    out = np.full((slots, n_cells), -1)
    if len(order):
        pick = starts[None, :] + np.arange(slots)[:, None] % np.maximum(counts, 1)[None, :]  # [slot, cell]
        out[:] = np.where(counts[None, :] > 0, order[np.minimum(pick, len(order) - 1)], -1)
    return out


def slot_beams(serving: np.ndarray, best_beam: np.ndarray, n_cells: int, slots: int) -> np.ndarray:
    """[slot, cell]: the beam each cell points in each slot, toward the UE it schedules then
    (:func:`scheduled_ues`); -1 for a cell that serves nobody."""
    ue = scheduled_ues(serving, n_cells, slots)
    return np.where(ue >= 0, np.asarray(best_beam)[np.maximum(ue, 0)], -1)


def slot_sinr_db(cells: Sequence[Cell], gains: Any, serving: np.ndarray, best_beam: np.ndarray,
                 beams: np.ndarray, noise_mw: np.ndarray, silent_idle: bool, device: Any = HOST,
                 linear: bool = False) -> Any:
    """[slot, ue, freq]: the SINR of every UE on its serving cell's best beam, the other cells
    on its carrier pointing ``beams`` [slot, cell] (:func:`slot_beams`), on the victim's channel
    ``gains`` [ue, cell, freq, beam] (linear; numpy, or a tensor on ``device``). A cell serving
    nobody is silent with ``silent_idle``, and otherwise sends over its codebook evenly (its mean
    beam gain).
    ``noise_mw`` [ue] (0: the SIR); NaN for a UE without a cell. Computed on the torch
    ``device`` (a setting or a ``torch.device``; at scale, tens of millions of products).
    ``linear``: the ratio itself, a float64 tensor left on the device (what a link level
    takes, :meth:`~caviar_plugins.radio.link_level.LinkLevel.run_linear`), not its dB in numpy."""
    import torch

    dev = resolve(device)
    terms = _terms(*_terms_inputs(cells, gains, serving, best_beam, beams, silent_idle, dev))
    out = _per_slot(terms, to_torch(np.asarray(noise_mw, dtype=float), dev, torch.float64), linear)
    return out if linear else to_numpy(out)


def slot_sinr_and_wideband(cells: Sequence[Cell], gains: Any, serving: np.ndarray, best_beam: np.ndarray,
                           beams: np.ndarray, noise_mw: np.ndarray, silent_idle: bool, weights: np.ndarray,
                           device: Any = HOST, linear: bool = False,
                           compiled: bool = False) -> tuple[Any, np.ndarray, np.ndarray]:
    """:func:`slot_sinr_db` [slot, ue, freq], and the SINR and the SIR [ue] (dB, numpy: NaN for a
    UE without a cell) of the frequencies' mean channel (weighted by ``weights`` [freq]) averaged
    over the slots, from one interference sum: the signal and the interference are linear in the
    gains, so the mean channel's are the means of the frequencies' (equal to summing again over
    the mean channel's gains, to float64's rounding). ``compiled``: the tensor work as one
    ``torch.compile`` program (the network's ``compile``; the same numbers to float64's rounding)."""
    work = compiled_once(__name__, "sinr_and_wideband_compiled", _sinr_and_wideband) if compiled \
        else _sinr_and_wideband
    per_slot, wide = work(*sinr_and_wideband_args(cells, gains, serving, best_beam, beams, noise_mw, silent_idle,
                                                  weights, device, linear))
    wide = to_numpy(wide)  # (the host's one read)
    return per_slot if linear else to_numpy(per_slot), wide[0], wide[1]


def sinr_and_wideband_args(cells: Sequence[Cell], gains: Any, serving: np.ndarray, best_beam: np.ndarray,
                           beams: np.ndarray, noise_mw: np.ndarray, silent_idle: bool, weights: np.ndarray,
                           device: Any = HOST, linear: bool = False) -> tuple:
    """:func:`_sinr_and_wideband`'s arguments for :func:`slot_sinr_and_wideband`'s, tensors on
    the torch ``device`` (and ``linear``): what a program that computes more at once takes
    (:func:`~caviar_plugins.network.sinrs.both_directions`)."""
    import torch

    dev = resolve(device)
    return (_terms_inputs(cells, gains, serving, best_beam, beams, silent_idle, dev),
            to_torch(np.asarray(noise_mw, dtype=float), dev, torch.float64),
            to_torch(np.asarray(weights, dtype=float), dev, torch.float64), linear)


def _sinr_and_wideband(inputs: tuple, noise: Any, w: Any, linear: bool) -> tuple[Any, Any]:
    """:func:`slot_sinr_and_wideband`'s tensor work on :func:`_terms_inputs`' ``inputs``: the
    per-slot SINR (:func:`_per_slot`) and the wideband SINR and SIR in dB [2, ue] (NaN: no cell)."""
    import torch

    signal, interference, unserved = terms = _terms(*inputs)
    mean_signal = (signal * w).sum(dim=-1) / w.sum()  # [ue]
    mean_interference = (interference * w).sum(dim=-1) / w.sum()  # [slot, ue]
    ratios = torch.stack([(mean_signal / (noise + mean_interference)).mean(dim=0),
                          (mean_signal / mean_interference).mean(dim=0)])
    return _per_slot(terms, noise, linear), torch.where(unserved[0, :, 0], float("nan"), 10 * torch.log10(ratios))


sinr_and_wideband_compiled: Any = None
""":func:`_sinr_and_wideband` compiled (``torch.compile``, once a process, by
:func:`~caviar_plugins.torch_device.compiled_once`; the UE count a dynamic size after its first
change): on a GPU a few kernels instead of about 30 launches."""


def _per_slot(terms: tuple[Any, Any, Any], noise: Any, linear: bool) -> Any:
    """[slot, ue, freq]: the SINR of :func:`_terms`' ``terms`` with ``noise`` [ue] (a tensor
    on their device; 0: the SIR), NaN for a UE without a cell: the ratio itself with ``linear``,
    else its dB (no signal: -inf; the SIR alone: NaN); a tensor."""
    import torch

    signal, interference, unserved = terms
    ratio = signal[None] / (noise[None, :, None] + interference)
    # (a mask, not an indexing: no wait on a GPU)
    return torch.where(unserved, float("nan"), ratio if linear else 10 * torch.log10(ratio))


def _terms_inputs(cells: Sequence[Cell], gains: Any, serving: np.ndarray, best_beam: np.ndarray,
                  beams: np.ndarray, silent_idle: bool, dev: Any) -> tuple:
    """:func:`_terms`' inputs, tensors on ``dev``: the gains [ue, cell, freq, beam], the power
    each UE hears of each other cell on its carrier [ue, cell, 1, 1], the cells' beams per slot as
    one-hot rows [slot, cell·beam], the idle cells [slot, cell] (None: silent), each UE, its cell
    and its best beam there [ue], the serving cell's power [ue, 1], the UEs without a cell [1, ue, 1]."""
    import torch

    n_ue, n_cell, n_f, n_beam = gains.shape
    n_slot = len(beams)
    power = 10 ** (np.array([c.tx_power_dbm for c in cells]) / 10)
    carrier = np.array([c.carrier_hz for c in cells])
    serving = np.asarray(serving)
    s = np.maximum(serving, 0)
    # Who interferes with whom: the other cells on the victim's carrier, weighted by power.
    heard = (carrier[None, :] == carrier[s][:, None]) & (np.arange(n_cell)[None, :] != s[:, None])  # [ue, cell]
    # A cell's beam in a slot as a one-hot row: the interference is one matrix product over
    # (cell, beam), not a gather of [slot, ue, cell, freq].
    beams = np.asarray(beams)
    pointing = (beams[:, :, None] == np.arange(n_beam)[None, None, :]).reshape(n_slot, n_cell * n_beam)
    idle = None if silent_idle else to_torch(beams < 0, dev, torch.float64)  # [slot, cell]
    ue, s_t, best_t = (to_torch(x, dev) for x in (np.arange(n_ue), s, np.asarray(best_beam)))
    heard_power = (power[None, :] * heard)[:, :, None, None]
    return (to_torch(gains, dev, torch.float64), to_torch(heard_power, dev, torch.float64),
            to_torch(pointing, dev, torch.float64), idle, ue, s_t, best_t,
            to_torch(power[s][:, None], dev, torch.float64), to_torch(serving < 0, dev)[None, :, None])


def _terms(g: Any, heard_power: Any, pointing: Any, idle: Any, ue: Any, s: Any, best: Any, power_s: Any,
           unserved: Any) -> tuple[Any, Any, Any]:
    """The terms of :func:`slot_sinr_db`'s ratio as float64 tensors of :func:`_terms_inputs`: the
    signal [ue, freq], the interference [slot, ue, freq], and which UEs have no cell [1, ue, 1]."""
    n_ue, n_cell, n_f, n_beam = g.shape
    weighted = g * heard_power  # [ue, cell, freq, beam]
    by_beam = weighted.permute(1, 3, 0, 2).reshape(n_cell * n_beam, n_ue * n_f)
    interference = (pointing @ by_beam).reshape(pointing.shape[0], n_ue, n_f)
    if idle is not None:  # a cell serving nobody sends over its codebook evenly
        mean = weighted.mean(dim=-1).permute(1, 0, 2).reshape(n_cell, n_ue * n_f)
        interference = interference + (idle @ mean).reshape(pointing.shape[0], n_ue, n_f)
    signal = power_s * g[ue, s, :, best]  # [ue, freq]
    return signal, interference, unserved


def scene_direction(cell: Cell, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[..., 3]: the unit direction (scene frame) in front of ``cell``'s panel with the
    spatial frequencies (u, v): the panel-frame vector ``(√(1 − u² − v²), u, v)`` rotated
    back by ``R = Rz(azimuth)·Ry(downtilt)`` (TR 38.901 §7.1.3; :func:`panel_frequencies`
    is its inverse). A pair past the visible region (``u² + v² > 1``, no direction has it)
    gives the nearest direction: (u, v) scaled to unit length, in the panel's plane."""
    u, v = np.asarray(u, dtype=float), np.asarray(v, dtype=float)
    r = np.hypot(u, v)
    u, v = np.where(r > 1, u / np.maximum(r, 1e-300), u), np.where(r > 1, v / np.maximum(r, 1e-300), v)
    x = np.sqrt(np.maximum(1.0 - u * u - v * v, 0.0))
    a, t = math.radians(cell.azimuth_deg), math.radians(cell.downtilt_deg)
    # Tilt the panel's (x, y, z) down by t about its y axis, then turn it to the azimuth.
    x, z = math.cos(t) * x + math.sin(t) * v, -math.sin(t) * x + math.cos(t) * v
    return np.stack([math.cos(a) * x - math.sin(a) * u, math.sin(a) * x + math.cos(a) * u, z], axis=-1)


def beam_report(cell: Cell, codebook: Codebook, beam: int) -> dict[str, float | int]:
    """A serving SSB beam for ``network.ue``: its index and where it points (azimuth from +x
    and elevation above the horizon, scene frame; the codebook's direction, not the UE's):
    the beam's (u, v) rotated back to the scene (:func:`scene_direction`), exact with a
    tilted panel."""
    u, v = codebook.pointing()[beam]
    d = scene_direction(cell, u, v)
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, float(d[2])))))
    azimuth = math.degrees(math.atan2(float(d[1]), float(d[0])))
    return {"ssb_beam": beam, "beam_azimuth_deg": round(azimuth % 360.0, 2),
            "beam_elevation_deg": round(elevation, 2)}
