"""Received power through Sionna RT, with its derivatives with respect to the scene's radio
materials: what a fit of the materials to measurements descends on
(:mod:`caviar_plugins.twin.fit`).

:class:`ReceivedPower` places receivers and transmitters (single antennas) in a scene, traces
every transmitter to every receiver in one solve, and gives, per measured (receiver,
transmitter) pair, the local-average received power in dBm:

    P = P_tx + 10·log10( Σ_paths |a_p|² )

the sum of the paths' powers (Sionna's coefficients ``a`` include the antenna patterns and
every interaction), which is what a power measurement averaged over the bandwidth or a few
wavelengths of track reports. With :meth:`ReceivedPower.loss_and_gradient`, the mean squared
error in dB over the pairs it is given and its gradient with respect to each material property
come from Dr.Jit's automatic differentiation through Sionna's field computation (the solver's
``loop_mode = "evaluated"``): a path's geometry does not depend on the materials, its
coefficient does.

So, with diffuse reflection off (``reuse_geometry``, the default then), the paths are traced
once per placement and only their fields are computed again for each material guess
(:func:`~caviar_plugins.rt.sionna_adapter.trace_geometry` and
:func:`~caviar_plugins.rt.sionna_adapter.path_powers`: Sionna's own solver split in its two
halves): the same powers as a whole solve with the same seed, at a fraction of its cost. With
diffuse reflection on, Sionna samples a diffuse bounce with a probability the scattering
coefficient sets, so every guess is traced afresh.

A trace of many receivers at once finds many (specular chain, receiver) pairs, more than
Sionna's table of the chains seen holds without collisions (it drops the pairs that collide,
silently): with the geometry traced once, the trace is made again with a larger table until
less than 1 % are lost (:func:`~caviar_plugins.rt.sionna_adapter.chain_table_slots`), so
that a receiver's power does not depend on the others traced with it. Whole solves (diffuse
reflection on) use the table such a trace grew, or Sionna's own, unwatched.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

from caviar_plugins.rt import sionna_adapter
from caviar_plugins.rt.drjit_setup import jit
from caviar_plugins.rt.materials import fix_at_carrier, material_of
from caviar_plugins.rt.scene import AntennaArray, planar_array, sionna_rt
from caviar_plugins.rt.settings import TraceSettings

Unknown = tuple[str, str]
"""(material, property): one quantity a fit can learn."""

RX_PREFIX, TX_PREFIX = "meas-rx-", "meas-tx-"


def binned_taps(delays_s: np.ndarray, powers: np.ndarray, resolution_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Taps or paths at ``delays_s`` (s) with linear ``powers`` binned at ``resolution_s`` from
    the earliest, as a sounder of that resolution (1/bandwidth) sees them: each bin's centre
    (s, on the delays' origin) and summed power, for the bins with a tap only (no array of the
    whole span: delays given in ns by mistake would make billions of bins)."""
    first = delays_s.min()
    bins, at = np.unique(np.floor((delays_s - first) / resolution_s + 1e-9), return_inverse=True)
    return first + (bins + 0.5) * resolution_s, np.bincount(at.reshape(-1), weights=powers)


def rms_delay_spread(delays_s: np.ndarray, powers: np.ndarray, resolution_s: float) -> float:
    """The RMS delay spread (s) of taps or paths at ``delays_s`` with linear ``powers``, binned
    first (:func:`binned_taps`): the same estimator for a sounder's taps and for ray-traced
    paths, so that both are seen at the measurement's bandwidth. NaN without power."""
    delays_s, powers = np.asarray(delays_s, dtype=np.float64), np.asarray(powers, dtype=np.float64)
    keep = powers > 0
    if not keep.any():
        return float("nan")
    t, p = binned_taps(delays_s[keep], powers[keep], resolution_s)
    t = t - t[0]
    mean = float(np.sum(p * t) / np.sum(p))
    return float(np.sqrt(max(float(np.sum(p * (t - mean) ** 2) / np.sum(p)), 0.0)))


class ReceivedPower:
    """The received power of measured pairs in ``scene`` (already loaded, at its carrier),
    traced as ``settings`` say with the solver's seed from ``seed``."""

    def __init__(self, scene: Any, settings: TraceSettings, seed: int = 0, antenna: AntennaArray | None = None,
                 reuse_geometry: bool | None = None):
        rt = sionna_rt()
        self.scene = scene
        fix_at_carrier(scene)
        array = planar_array(antenna or AntennaArray())
        scene.tx_array = array
        scene.rx_array = array
        self.options = settings.path_options(seed)
        self.max_num_paths_per_src = settings.max_num_paths_per_src
        self._solver = rt.PathSolver()
        self._diff_solver = rt.PathSolver()
        self._diff_solver.loop_mode = "evaluated"
        self.n_rx = self.n_tx = 0
        if reuse_geometry is None:
            reuse_geometry = not settings.diffuse_reflection and sionna_adapter.problem() is None
        elif reuse_geometry and settings.diffuse_reflection:
            raise ValueError("reuse_geometry: a diffuse bounce is sampled with a probability the materials set, "
                             "so paths traced with diffuse_reflection cannot be reused")
        self.reuse_geometry = bool(reuse_geometry)
        """Trace once per placement and compute only the fields for each material guess."""
        self._traced: Any = None
        self.solves = 0
        """Whole traces made (the count a fit's cost follows)."""
        self.chain_slots = 0
        """Slots per source of Sionna's specular-chain tables (0: its own, 1e6), grown by a
        trace that found too many chains for them (:meth:`_trace`)."""
        self.chain_loss = 0.0
        """The share of specular chains the last trace lost to collisions, to first order."""
        self.field_evaluations = 0

    def place(self, rx_positions: np.ndarray, tx_positions: np.ndarray) -> None:
        """Receivers at ``rx_positions`` (N × 3, m) and transmitters at ``tx_positions``
        (M × 3), in place of those the scene had."""
        rt = sionna_rt()
        for name in list(self.scene.receivers):
            self.scene.remove(name)
        for name in list(self.scene.transmitters):
            self.scene.remove(name)
        for i, p in enumerate(np.asarray(tx_positions, dtype=float).reshape(-1, 3)):
            self.scene.add(rt.Transmitter(f"{TX_PREFIX}{i}", position=[float(v) for v in p]))
        for i, p in enumerate(np.asarray(rx_positions, dtype=float).reshape(-1, 3)):
            self.scene.add(rt.Receiver(f"{RX_PREFIX}{i}", position=[float(v) for v in p]))
        self.n_rx, self.n_tx = len(self.scene.receivers), len(self.scene.transmitters)
        self._traced = None

    def _set(self, values: Mapping[Unknown, float], grad: bool) -> dict[Unknown, Any]:
        dr, mi = jit()
        handles = {}
        for (material, prop), v in values.items():
            x = dr.opaque(mi.Float, float(v))  # not a literal: one kernel for every value
            if grad:
                dr.enable_grad(x)
            setattr(material_of(self.scene, material), prop, x)
            handles[(material, prop)] = x
        return handles

    def _pair_power(self, solver: Any, pairs: np.ndarray) -> Any:
        """Σ|a|² per pair (a Dr.Jit array, in pair order) for ``pairs`` ((rx, tx) rows)."""
        if self.reuse_geometry:
            return self._pair_power_reused(solver, pairs)
        dr, mi = jit()
        a_re, a_im = self._whole_solve(solver).a
        power = dr.square(a_re) + dr.square(a_im)  # [rx, rx_ant, tx, tx_ant, paths]
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if power.shape[-1] == 0:  # no path at all (Dr.Jit cannot sum an empty axis)
            return dr.zeros(mi.Float, len(pairs))
        n_ant = power.shape[1] * power.shape[3]
        per_pair = dr.sum(dr.sum(dr.sum(power, axis=-1), axis=3), axis=1) / n_ant  # [rx, tx]
        index = mi.UInt32(pairs[:, 0] * self.n_tx + pairs[:, 1])
        return dr.gather(mi.Float, per_pair.array, index)

    def _trace(self) -> Any:
        """The paths' geometry, traced again with larger specular-chain tables while the
        first trace's lost more than :data:`~caviar_plugins.rt.sionna_adapter.CHAIN_LOSS` of
        its chains to hash collisions (many receivers in one solve; see
        :func:`~caviar_plugins.rt.sionna_adapter.chain_table_slots`)."""
        while True:
            with sionna_adapter.chain_table(self.chain_slots):
                traced = sionna_adapter.trace_geometry(
                    self._solver, self.scene, max_num_paths_per_src=self.max_num_paths_per_src, **self.options)
            self.solves += 1
            per_source = int(np.bincount(np.array(traced.source_indices, dtype=np.int64)).max(initial=0))
            self.chain_loss, size, grown = sionna_adapter.chain_table_check(
                per_source, self.max_num_paths_per_src, self.chain_slots, self.n_tx)
            if not grown:
                break
            self.chain_slots = grown
        if self.chain_loss > sionna_adapter.CHAIN_LOSS:
            warnings.warn(sionna_adapter.chain_loss_warning(self.chain_loss, size, "trace fewer receivers at once"),
                          RuntimeWarning, stacklevel=4)
        return traced

    def _geometry(self) -> Any:
        """The paths traced at this placement (traced on first use, :meth:`_trace`)."""
        if self._traced is None:
            self._traced = self._trace()
        return self._traced

    def _whole_solve(self, solver: Any) -> Any:
        """Sionna's ``Paths`` of one whole solve by ``solver`` (materials as they are now)."""
        self.solves += 1
        with sionna_adapter.chain_table(self.chain_slots):
            return solver(self.scene, max_num_paths_per_src=self.max_num_paths_per_src, synthetic_array=True,
                          **self.options)

    def _pair_power_reused(self, solver: Any, pairs: np.ndarray) -> Any:
        dr, mi = jit()
        traced = self._geometry()
        self.field_evaluations += 1
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        per_pair = dr.zeros(mi.Float, self.n_rx * self.n_tx)
        if traced.num_paths:
            power = sionna_adapter.path_powers(solver, self.scene, traced)
            pair_of_path = traced.target_indices * self.n_tx + traced.source_indices
            dr.scatter_reduce(dr.ReduceOp.Add, per_pair, power, pair_of_path)
        return dr.gather(mi.Float, per_pair, mi.UInt32(pairs[:, 0] * self.n_tx + pairs[:, 1]))

    def power_delay_profiles(self, pairs: np.ndarray, resolution_s: float,
                             values: Mapping[Unknown, float] | None = None
                             ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Each (rx, tx) pair's power-delay profile at the scene's materials (``values`` set
        first), as a sounder of resolution ``resolution_s`` (1/bandwidth) reports it: its
        paths' powers (path gain, linear) binned (:func:`binned_taps`), ``(bin centres (s),
        gains)``; None where no path joins the pair."""
        if values:
            self._set(values, grad=False)
        tau, power, pair_of_path = self._paths_now()
        order = np.argsort(pair_of_path, kind="stable")
        starts = np.searchsorted(pair_of_path[order], np.arange(self.n_rx * self.n_tx + 1))
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        for rx, tx in np.asarray(pairs, dtype=np.int64).reshape(-1, 2):
            k = order[starts[rx * self.n_tx + tx]:starts[rx * self.n_tx + tx + 1]]
            k = k[power[k] > 0]
            out.append(binned_taps(tau[k], power[k], resolution_s) if len(k) else None)
        return out

    def delay_spreads(self, pairs: np.ndarray, resolution_s: float,
                      values: Mapping[Unknown, float] | None = None) -> np.ndarray:
        """Each (rx, tx) pair's RMS delay spread (s) from its :meth:`power_delay_profiles`
        (:func:`rms_delay_spread`); NaN where no path. ``values`` sets material properties
        first."""
        return np.array([np.nan if prof is None else rms_delay_spread(prof[0], prof[1], resolution_s)
                         for prof in self.power_delay_profiles(pairs, resolution_s, values)])

    def _paths_now(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every traced path's delay (s), power (linear path gain, 0: no field) and pair
        (rx · n_tx + tx), at the materials now."""
        if self.reuse_geometry:
            traced = self._geometry()
            if not traced.num_paths:
                return np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64)
            power = np.array(sionna_adapter.path_powers(self._solver, self.scene, traced), dtype=np.float64)
            self.field_evaluations += 1
            pair_of_path = (np.array(traced.target_indices, dtype=np.int64) * self.n_tx
                            + np.array(traced.source_indices, dtype=np.int64))
            return sionna_adapter.path_delays(traced), power, pair_of_path
        paths = self._whole_solve(self._solver)  # delays [rx, tx, path], coefficients [rx, ., tx, ., path]
        a_re, a_im = (np.array(c, dtype=np.float64) for c in paths.a)
        power = (a_re**2 + a_im**2).mean(axis=(1, 3)).reshape(-1)
        pairs = max(self.n_rx * self.n_tx, 1)
        return (np.array(paths.tau, dtype=np.float64).reshape(-1), power,
                np.repeat(np.arange(pairs), power.size // pairs))

    def predict(self, pairs: np.ndarray, tx_power_dbm: np.ndarray | float,
                values: Mapping[Unknown, float] | None = None) -> np.ndarray:
        """Received power (dBm) of each (rx, tx) pair; -inf where no path joins them.
        ``values`` sets material properties first."""
        if values:
            self._set(values, grad=False)
        power = np.array(self._pair_power(self._solver, pairs), dtype=np.float64)
        with np.errstate(divide="ignore"):
            return np.asarray(tx_power_dbm, dtype=np.float64) + 10.0 * np.log10(power)

    def loss_and_gradient(self, pairs: np.ndarray, tx_power_dbm: np.ndarray | float, measured_dbm: np.ndarray,
                          weights: np.ndarray, values: Mapping[Unknown, float]
                          ) -> tuple[np.ndarray, float, dict[Unknown, float]]:
        """For material properties ``values``: the predicted dBm of every pair (-inf: no
        path), the weighted mean squared error Σ w·(P − measured)² / Σ w over the pairs
        with a path (dB²), and its derivative with respect to each property of ``values``."""
        dr, mi = jit()
        handles = self._set(values, grad=True)
        power = self._pair_power(self._diff_solver, pairs)
        dr.eval(power)
        p = np.array(power, dtype=np.float64)
        w = np.where(p > 0, np.asarray(weights, dtype=np.float64), 0.0)
        if w.sum() <= 0:
            raise ValueError("no measured pair that is fitted has a ray-traced path in the scene")
        tx = np.broadcast_to(np.asarray(tx_power_dbm, dtype=np.float64), p.shape)
        target = mi.Float((np.asarray(measured_dbm, dtype=np.float64) - tx).astype(np.float32))
        db = 10.0 * dr.log(dr.maximum(power, 1e-30)) / np.log(10.0)
        loss = dr.sum(mi.Float((w / w.sum()).astype(np.float32)) * dr.square(db - target))
        dr.backward(loss)
        grads = {key: float(dr.grad(x)[0]) for key, x in handles.items()}
        with np.errstate(divide="ignore"):
            predicted = tx + 10.0 * np.log10(p)
        return predicted, float(loss[0]), grads

