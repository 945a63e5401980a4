"""The ``ray-traced`` channel: every site traced in one Sionna RT solve
(:class:`~caviar_plugins.network.raytraced.SiteTracer`) every ``evolution.refresh_s`` of
virtual time and when a UE appears, and in between each path's phase turned as its UE
moves (:class:`~caviar_plugins.network.raytraced.TracedChannels`, ``evolution.mode =
"doppler"``) or the paths' power sum held (``"hold"``)."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Sequence

import numpy as np

import caviar
from caviar_plugins.network.beams import beam_responses, gains_of_responses
from caviar_plugins.network.cells import Cell
from caviar_plugins.network.channel import UePlaces
from caviar_plugins.network.raytraced import EvolvingPaths, SiteTracer, TracedChannels, summed_db
from caviar_plugins.torch_device import to_torch


class RayTracedChannel:
    kind = "ray-traced"
    directions = True

    def __init__(self, params: Any, cells: Sequence[Cell], *, link: Any, device: Any, seed: int,
                 base_dir: pathlib.Path | None = None):
        """``params``: the network's (its ``scene``, ``raytracing``, ``evolution``, ``layout``);
        ``link``: its :class:`~caviar_plugins.radio.link_settings.LinkSettings` (the subbands the
        channel is evaluated at); ``device``: the resolved torch device."""
        self.cells, self.evolution, self.device = list(cells), params.evolution, device
        self.tracer = SiteTracer(params.scene, params.raytracing, self.cells, seed=seed, base_dir=base_dir,
                                 paths_per_link=params.evolution.paths_per_link)
        layout = params.layout
        if layout is not None:
            covered = [c.site for c in self.cells if not self.tracer.outdoors(np.array([c.position]))[0]]
            if covered:
                raise caviar.ConfigError(
                    f"the layout puts site(s) {', '.join(dict.fromkeys(covered))} under a roof of "
                    f"{params.scene!r} (no open sky above {layout.height_m:g} m): move the layout "
                    f"with layout.center_m (now {list(layout.center_m)})", "params.layout.center_m")
        self.flat = self.evolution.mode == "hold"
        self.frequencies = link.subband_frequencies_hz
        # One subband: the band's power averaged over 8 frequencies, not one point's fade.
        self.band_average = len(self.frequencies) == 1
        if self.band_average:
            self.frequencies = dataclasses.replace(link, subbands=min(8, link.num_prb)).subband_frequencies_hz
        self.channels: TracedChannels | None = None  # the last trace, rows in self.traced order
        self.responses: tuple[TracedChannels | None, Any] = (None, None)  # (a trace, its paths' beam responses)
        self.traced: dict[str, int] = {}  # UE_Id -> row of self.channels
        self._rows: tuple[Any, np.ndarray] = (None, np.zeros(0, dtype=np.int64))  # (ids, their rows) of the trace
        self.refreshed_at = -np.inf  # the last refresh on the refresh_s schedule
        self.amplitude: Any = None  # the step's evolved path amplitudes (the beams' too)
        # (the trace, the rows of it, and those rows' paths on the device (EvolvingPaths) and beam
        # responses: made once a trace or a change of the UEs, not each step)
        self._evolving: tuple[Any, Any, Any] = (None, None, None)
        self._responses_of_rows: tuple[Any, Any, Any] = (None, None, None)

    def _traced_rows(self, ids: list[str]) -> np.ndarray:
        """The rows of the last trace of ``ids`` (looked up again only when the UEs change)."""
        if self._rows[0] is not ids:
            self._rows = (ids, np.array([self.traced[u] for u in ids], dtype=np.int64))
        return self._rows[1]

    def gains_db(self, t: float, ues: UePlaces) -> Any:
        """Numpy with ``evolution.mode = "hold"``; else a float64 tensor on the device, as the
        step's beam gains (:meth:`beam_gains`) are (the network reads what it needs of them)."""
        import torch

        ids, pos = ues.ids, ues.positions
        due = t - self.refreshed_at >= self.evolution.refresh_s - 1e-9
        if due or (self._rows[0] is not ids and any(u not in self.traced for u in ids)):
            self.channels = self.tracer.trace(pos)  # (a new UE is traced, with all, at once)
            self.traced = {u: i for i, u in enumerate(ids)}
            self._rows = (ids, np.arange(len(ids)))
            if due:
                self.refreshed_at = t
        assert self.channels is not None
        rows = self._traced_rows(ids)
        if self.flat:
            return self.channels.power_sum_db[rows][..., None]
        if self._evolving[0] is not self.channels or self._evolving[1] is not rows:
            self._evolving = (self.channels, rows, EvolvingPaths(self.channels.rows(rows), self.device,
                                                                 self.frequencies))
        self.amplitude = self._evolving[2].at(pos)  # (the beams' too; once a step)
        gains = summed_db(self.amplitude, keep=True)  # (left on the device: read only where it is needed)
        if self.band_average:
            return 10 * torch.log10(torch.mean(10 ** (gains / 10), dim=-1, keepdim=True))
        return gains

    def beam_gains(self, ues: UePlaces, codebooks: Sequence[Any]) -> Any:
        """From the paths :meth:`gains_db` just moved (their beam responses kept until the
        next trace): a float64 tensor on the device, where the step's SINRs are computed."""
        ch = self.channels
        assert ch is not None and ch.departure is not None
        if self.responses[0] is not ch:  # (kept on the device, from one trace to the next)
            self.responses = (ch, beam_responses(self.cells, codebooks, ch.departure, self.device))
        rows = self._traced_rows(ues.ids)
        amplitude = ch.amplitude[rows][..., None] if self.flat else self.amplitude
        if self._responses_of_rows[0] is not self.responses[1] or self._responses_of_rows[1] is not rows:
            r = self.responses[1]  # (the rows' responses gathered once a trace or a change of the UEs)
            self._responses_of_rows = (r, rows, r[to_torch(rows, r.device)])
        gains = gains_of_responses(amplitude, self._responses_of_rows[2], keep=True)  # (a tensor on the device)
        if self.band_average:
            gains = gains.mean(dim=2, keepdim=True)
        return gains

    def forget(self, ue: str) -> None:
        self.traced.pop(ue, None)  # (traced again where it next is)
        self._rows = (None, self._rows[1])

    def outdoors(self, points: np.ndarray) -> np.ndarray:
        return self.tracer.outdoors(points)

    def state(self) -> dict[str, Any]:
        # The tracer comes from setup; the last trace (the channels evolve from it until the
        # next refresh) and whether the shoot cache had seen the scene are the state.
        return {"channels": self.channels, "traced": self.traced, "refreshed_at": self.refreshed_at,
                "cache_seen": self.tracer.cache_seen()}

    def restore(self, state: dict[str, Any]) -> None:
        self.channels, self.traced, self.refreshed_at = state["channels"], state["traced"], state["refreshed_at"]
        self._rows = (None, self._rows[1])
        if state.get("cache_seen") and self.channels is not None:
            # The shoot cache had seen the scene: one trace where the UEs last were lets it see
            # it again (its result is not used), so the next trace is served as it would have been.
            self.tracer.trace(self.channels.position)
