"""Ray-traced path gains for the radio network: every site traced in one Sionna RT solve.

The sectors of a site share its position, so one trace per site serves all of them:
each site is one isotropic transmitter, each UE one isotropic receiver, and a sector's
gain toward a UE is the sum over the paths of their power times the sector's element
pattern at the path's departure direction::

    G(sector, ue) = Σ_paths |a_p|² · g_sector(θ_t,p, φ_t,p)

(wideband: the paths add in power, as over a band much wider than the coherence
bandwidth). The pattern is :func:`caviar_plugins.network.cells.element_gain_db`'s, on
the departure angles instead of the straight line, so the free-space model and this one
agree where only the direct path exists (tested).

Between two traces the channel is not frozen: :meth:`SiteTracer.trace` keeps every
path's complex baseband amplitude b_p (the sector's field pattern applied), delay τ_p
and direction of arrival k̂_p, and :class:`TracedChannels` evolves them as the UE moves
by d from where it was traced (the scene static, each path a plane wave at the UE)::

    H(cell, ue; f) = Σ_paths b_p · exp(−j2π f τ_p) · exp(j2π (f_c + f) k̂_p·d / c)

at baseband frequencies ``f`` (the subbands' centres): fast fading in space, hence in
time (at velocity v the phase turns at the Doppler shift f_D = v·k̂_p/λ, Sionna RT's
``Paths.doppler``), and in frequency (the delay spread), as Sionna RT's ``Paths.cfr``
computes over time steps, but for any trajectory between two traces.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Sequence

import numpy as np

from caviar_plugins.constants import SPEED_OF_LIGHT
from caviar_plugins.network.cells import Cell, pattern_gain_db
from caviar_plugins.rt.scene import AntennaArray, Emitter, build_scene, receiver
from caviar_plugins.rt.settings import TraceSettings
from caviar_plugins.torch_device import HOST, resolve, to_numpy, to_torch

NO_PATH_DB = -250.0
"""The gain of a cell no traced path connects to a UE: far below any noise floor."""
EVOLUTIONS = ("doppler", "hold")


NETWORK_RAYS = TraceSettings(samples_per_src=100_000, max_depth=3, diffuse_reflection=False, refraction=False)
"""The network's ``raytracing`` defaults: 1e5 rays per site to depth 3, the line of sight,
specular reflection and diffraction (every site in one solve, refreshed every second)."""


@dataclasses.dataclass(frozen=True)
class Evolution:
    """How the ray-traced channel is kept between two traces (``evolution = { … }``)."""

    refresh_s: float = 1.0
    """Virtual seconds between two traces."""
    mode: str = "doppler"
    """Between traces: ``doppler`` (each path's phase turns as the UE moves, at its
    Doppler shift, see :class:`TracedChannels`) or ``hold`` (the paths' power sum, frozen)."""
    paths_per_link: int = 16
    """The strongest paths kept per cell and UE for the evolution (the rest are weaker
    than the noise of the sum)."""

    def __post_init__(self):
        if not self.refresh_s > 0:
            raise ValueError(f"refresh_s: expected a positive number of seconds, got {self.refresh_s}")
        if self.mode not in EVOLUTIONS:
            raise ValueError(f"mode: expected one of {list(EVOLUTIONS)}, got {self.mode!r}")
        if isinstance(self.paths_per_link, bool) or self.paths_per_link < 1:
            raise ValueError(f"paths_per_link: expected >= 1, got {self.paths_per_link}")


@dataclasses.dataclass
class TracedChannels:
    """The paths of every cell toward every UE of one trace, kept to evolve the channel.

    ``amplitude`` [ue, cell, path] complex baseband coefficients (the sector's field
    pattern applied; 0: no path), ``delay_s`` [ue, cell, path], ``arrival`` [ue, cell,
    path, 3] unit vectors from the UE toward where each path arrives from, ``position``
    [ue, 3] where the UEs were traced, ``carrier_hz``."""

    amplitude: np.ndarray
    delay_s: np.ndarray
    arrival: np.ndarray
    position: np.ndarray
    carrier_hz: float
    power_sum_db: np.ndarray
    """[ue, cell]: every traced path's power summed (dB), the wideband gain with no fading."""
    departure: np.ndarray | None = None
    """[ue, cell, path, 3] unit vectors from the cell along which each path leaves (what a
    beam codebook acts on: :func:`caviar_plugins.network.beams.beam_gains`)."""

    def doppler_hz(self, velocity: np.ndarray) -> np.ndarray:
        """[ue, cell, path]: each path's Doppler shift v·k̂/λ for UE velocities [ue, 3] (m/s)."""
        return np.einsum("ucpk,uk->ucp", self.arrival, velocity) * self.carrier_hz / SPEED_OF_LIGHT

    def amplitudes(self, position: np.ndarray, frequencies_hz: np.ndarray) -> np.ndarray:
        """[ue, cell, path, freq]: each path's coefficient with the UEs at ``position`` [ue, 3],
        at baseband ``frequencies_hz`` (offsets from the carrier)."""
        return to_numpy(self.amplitudes_on(HOST, position, frequencies_hz))

    def amplitudes_on(self, device: Any, position: np.ndarray, frequencies_hz: np.ndarray) -> Any:
        """:meth:`amplitudes` as a complex128 tensor on the torch ``device`` (a setting or a
        ``torch.device``), computed there: a step's channel at scale is millions of phases."""
        return EvolvingPaths(self, device, frequencies_hz).at(position)

    def gain_db(self, position: np.ndarray, frequencies_hz: np.ndarray) -> np.ndarray:
        """[ue, cell, freq]: |H|² (dB) with the UEs at ``position`` [ue, 3], at baseband
        ``frequencies_hz`` (offsets from the carrier)."""
        return summed_db(self.amplitudes_on(HOST, position, frequencies_hz))

    def rows(self, index: np.ndarray) -> TracedChannels:
        return TracedChannels(self.amplitude[index], self.delay_s[index], self.arrival[index],
                              self.position[index], self.carrier_hz, self.power_sum_db[index],
                              None if self.departure is None else self.departure[index])


class EvolvingPaths:
    """One trace's paths (:class:`TracedChannels`, the step's UEs' rows) on the torch ``device``
    with what does not change until the next trace there too (the amplitudes, directions of
    arrival, each path's delay times the ``frequencies_hz``): a step's :meth:`at` converts
    and copies nothing of the size of the paths, only the UEs' displacements enter."""

    def __init__(self, ch: TracedChannels, device: Any, frequencies_hz: np.ndarray):
        import torch

        self.device = dev = resolve(device)
        self.position, self._torch = ch.position, torch
        f = to_torch(frequencies_hz, dev, torch.float64)
        self.carrier_f = ch.carrier_hz + f
        self.arrival = to_torch(ch.arrival, dev, torch.float64)
        self.delay_f = to_torch(ch.delay_s, dev, torch.float64)[..., None] * f
        self.amplitude = to_torch(ch.amplitude, dev, torch.complex128)[..., None]
        # (the phases, their unit phasors' magnitudes and the coefficients [ue, cell, path, freq]:
        # made once, written in place each step; at 1,000 UEs each is tens of MB, which made fresh
        # every step cost more in page faults and frees on a CPU than the arithmetic itself. Laid
        # out [ue, cell, freq, path], viewed as [ue, cell, path, freq]: the beams' product over the
        # paths (gains_of_responses) then reads them as they lie, without a copy)
        u, c, p, k = self.delay_f.shape
        self.delay_f = self.delay_f.transpose(2, 3).contiguous().transpose(2, 3)
        self._phase = torch.empty((u, c, k, p), dtype=torch.float64, device=dev).transpose(2, 3)
        self._unit = torch.ones((u, c, k, p), dtype=torch.float64, device=dev).transpose(2, 3)
        self._coefficients = torch.empty((u, c, k, p), dtype=torch.complex128, device=dev).transpose(2, 3)

    def at(self, position: np.ndarray) -> Any:
        """[ue, cell, path, freq]: each path's coefficient with the UEs at ``position`` [ue, 3]
        (:class:`TracedChannels`' evolution, a complex128 tensor on the device). The same
        tensor each call, written over: what a step keeps of it, it copies."""
        torch = self._torch
        moved = to_torch(np.asarray(position, dtype=float) - self.position, self.device, torch.float64)
        shorter = torch.einsum("ucpk,uk->ucp", self.arrival, moved)  # m
        # 2π (f·shorter/c − τ·f), in place: the same numbers as the expression made afresh
        phase = torch.mul(self.carrier_f, (shorter / SPEED_OF_LIGHT)[..., None], out=self._phase)
        phase.sub_(self.delay_f).mul_(2 * np.pi)
        return torch.polar(self._unit, phase, out=self._coefficients).mul_(self.amplitude)


def summed_db(amplitudes: Any, keep: bool = False) -> Any:
    """[ue, cell, freq]: |Σ_paths a|² (dB) of path coefficients [ue, cell, path, freq]
    (:meth:`TracedChannels.amplitudes`, numpy, or :meth:`TracedChannels.amplitudes_on`, a
    tensor, summed where it is), floored at ``NO_PATH_DB``. ``keep``: the float64 tensor left
    where it was computed, not numpy."""
    import torch

    a = amplitudes if isinstance(amplitudes, torch.Tensor) else to_torch(amplitudes, HOST)
    power = torch.abs(a.sum(dim=-2)) ** 2
    db = 10 * torch.log10(torch.clamp(power, min=10 ** (NO_PATH_DB / 10)))
    return db if keep else to_numpy(db)


class SiteTracer:
    """The network's sites in a Sionna RT scene; :meth:`gains_db` traces the UEs. A client of
    :mod:`caviar_plugins.rt`: the scene from :func:`~caviar_plugins.rt.scene.load_scene`, the
    solves by a :class:`~caviar_plugins.rt.solver.PathTracer` (shoot cache, path-buffer watch)."""

    def __init__(self, scene: str, settings: TraceSettings, cells: Sequence[Cell], seed: int = 0,
                 base_dir: pathlib.Path | None = None, paths_per_link: int = 16):
        from caviar_plugins.rt.solver import PathTracer

        self.s, self.cells, self.paths_per_link = settings, list(cells), paths_per_link
        carriers = {c.carrier_hz for c in cells}
        if len(carriers) > 1:
            raise ValueError("raytracing: every cell must share one carrier (one solve per carrier is not "
                             f"supported yet), got {sorted(carriers)}")
        self.sites: list[str] = list(dict.fromkeys(c.site for c in self.cells))
        first = {c.site: c for c in reversed(self.cells)}  # (a site's position: its first cell's)
        iso = AntennaArray()
        self.scene = build_scene(scene, base_dir, frequency_hz=carriers.pop(), tx_array=iso, rx_array=iso,
                                 transmitters=[Emitter(f"site-{site}", first[site].position) for site in self.sites],
                                 threads=settings.threads)
        self.site_of = np.array([self.sites.index(c.site) for c in self.cells])
        self.tracer = PathTracer(self.scene, settings, seed=seed)
        self.receivers: list[str] = []

    def cache_seen(self) -> bool:
        """Whether the shoot cache saw the last trace's geometry
        (:attr:`~caviar_plugins.rt.solver.PathTracer.cache_seen`)."""
        return self.tracer.cache_seen

    def outdoors(self, points: np.ndarray) -> np.ndarray:
        """Whether each point [n, 3] has open sky above it in the scene
        (:func:`~caviar_plugins.rt.scene.open_sky`): not inside a building."""
        from caviar_plugins.rt.scene import open_sky

        return open_sky(self.scene, points)

    def _place(self, ues: np.ndarray) -> None:
        n = len(ues)
        while len(self.receivers) < n:
            name = f"ue-{len(self.receivers)}"
            self.scene.add(receiver(name, [0.0, 0.0, 0.0]))
            self.receivers.append(name)
        while len(self.receivers) > n:
            self.scene.remove(self.receivers.pop())
        for name, p in zip(self.receivers, ues, strict=True):
            self.scene.receivers[name].position = [float(x) for x in p]

    def gains_db(self, ues: np.ndarray) -> np.ndarray:
        """Path gain (dB) of every cell toward every UE, its sector pattern included:
        [n_ue, n_cell], the paths' power sum; :data:`NO_PATH_DB` where no path reaches.
        One solve for every site."""
        return self.trace(ues).power_sum_db

    def trace(self, ues: np.ndarray) -> TracedChannels:
        """Every cell's paths toward the UEs at ``ues`` [n_ue, 3], the strongest
        ``paths_per_link`` per cell and UE. One solve for every site."""
        n_ue, n_cell, k = len(ues), len(self.cells), self.paths_per_link
        carrier = float(self.scene.frequency[0])
        if n_ue == 0:
            z = np.zeros((0, n_cell, k))
            return TracedChannels(z.astype(complex), z, np.zeros((0, n_cell, k, 3)), np.zeros((0, 3)), carrier,
                                  np.zeros((0, n_cell)), np.zeros((0, n_cell, k, 3)))
        self._place(ues)
        paths = self.tracer.solve()
        a_re, a_im = (np.array(x) for x in paths.a)  # [rx, rx_ant, tx, tx_ant, paths]
        a = (a_re + 1j * a_im)[:, 0, :, 0, :]  # [rx, tx, paths]
        shape = a.shape
        valid = np.array(paths.valid).reshape(shape)
        theta = np.degrees(np.array(paths.theta_t).reshape(shape))  # zenith of departure
        phi = np.degrees(np.array(paths.phi_t).reshape(shape))  # azimuth of departure
        theta_r, phi_r = (np.array(x).reshape(shape) for x in (paths.theta_r, paths.phi_r))
        arrival = np.stack([np.sin(theta_r) * np.cos(phi_r), np.sin(theta_r) * np.sin(phi_r), np.cos(theta_r)], -1)
        th, ph = np.radians(theta), np.radians(phi)
        leaving = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
        tau = np.array(paths.tau).reshape(shape).astype(float)
        # Sionna's a excludes the carrier's phase: the baseband coefficient is a·exp(-j2π f_c τ).
        a = np.where(valid, a * np.exp(-2j * np.pi * carrier * tau), 0.0)
        amp = np.zeros((n_ue, n_cell, k), dtype=complex)
        delay = np.zeros((n_ue, n_cell, k))
        toward = np.zeros((n_ue, n_cell, k, 3))
        departs = np.zeros((n_ue, n_cell, k, 3))
        total = np.zeros((n_ue, n_cell))
        kept = min(k, shape[-1])
        for c, cell in enumerate(self.cells):
            site = self.site_of[c]
            b = a[:, site] * 10 ** (pattern_gain_db(cell, theta[:, site], phi[:, site]) / 20)
            total[:, c] = (np.abs(b) ** 2).sum(axis=-1)
            keep = np.argsort(-np.abs(b), axis=-1)[:, :kept]
            amp[:, c, :kept] = np.take_along_axis(b, keep, axis=-1)
            delay[:, c, :kept] = np.take_along_axis(tau[:, site], keep, axis=-1)
            toward[:, c, :kept] = np.take_along_axis(arrival[:, site], keep[..., None], axis=1)
            departs[:, c, :kept] = np.take_along_axis(leaving[:, site], keep[..., None], axis=1)
        return TracedChannels(amp, delay, toward, np.array(ues, dtype=float), carrier,
                              10 * np.log10(np.maximum(total, 10 ** (NO_PATH_DB / 10))), departs)
