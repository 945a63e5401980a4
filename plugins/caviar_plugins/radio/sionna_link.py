"""Communications module: Sionna RT ray tracing in the loop.

Every step it places all UAVs (receivers and metal bodies) at their latest
positions, ray traces them in one solver call and publishes, per UAV:

* ``communications.throughput`` — paper schema ``{UE_type, UE_Id, throughput}`` in
  Mbit/s, for the beam pair chosen by the AI module (latest message on
  ``ai.beam.selection`` ``{"UE_Id": …, "beam_pair": i}``), else for the best pair;
* ``communications.link`` — LOS flag, best and used pair, path gain, SNR, paths;
* ``communications.channel.<UE_Id>`` — H (N_rx_ant × N_tx_ant, complex64), binary;
* ``communications.beam_gains.<UE_Id>`` — gains of all pairs (C_rx × C_tx, float32), binary;

and then ``communications.state`` ``"Ready"``. Beam pair index = rx_beam · 64 + tx_beam.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.radio.link_budget import LinkBudget
from caviar_plugins.radio.link_report import LINK_TOPICS, link_messages
from caviar_plugins.radio.scene import LookaheadTracer, RadioConfig, RadioScene
from caviar_plugins.schema import BEAM_SELECTION, FORECAST, POSITIONS, STATE, read_position


@dataclasses.dataclass
class SionnaLinkParams(RadioConfig):
    bandwidth_hz: float = 40e6
    tx_power_w: float = 0.5
    interference_dbw: float = -130.0
    publish_channels: bool = True
    """Publish H and the beam gains as binary payloads."""
    protocol: str = "physical"
    """``physical``: H with path loss, the link budget above, the Kronecker codebook at
    ``spacing``. ``paper``: the 2023 code's link (docs/paper-protocol.md): LOS path
    dropped, unit-energy H, no refraction or diffuse reflection, 5.714 λ spacing, the
    flat 64-point DFT, Rx 8.23 m below the UAV, R = 40 MHz · log2(1 + |g|²/3248.11).
    It fixes those fields whatever they are set to."""
    lookahead: bool = False
    """Look-ahead ray tracing (:class:`~caviar_plugins.radio.scene.LookaheadTracer`):
    one solve traces each UE's current position and the next ``lookahead_steps``
    positions of its ``3D.mobility.forecast`` (waypoint-flight's ``forecast_steps``),
    and later steps whose positions are within ``cache_tolerance_m`` of a traced one
    reuse its channel without a solve. Needs ``uav_mesh = false`` (moving UAV bodies
    cannot be at their current and future positions in one solve)."""
    lookahead_steps: int = 4
    """Forecast positions traced per UE and solve (receivers per solve: UEs × (1 + this))."""
    cache_tolerance_m: float = 0.01
    """A position within this distance of a traced one reuses its channel."""

    def __post_init__(self):
        paper.check_protocol(self.protocol)
        if self.protocol == "paper":
            self.spacing = paper.PAPER_SPACING
            self.los = False
            self.diffuse_reflection = False
            self.refraction = False
            self.specular_reflection = True
            self.diffraction = True
            self.codebook = "flat-dft"
            self.normalize = True
            self.antenna_offset = list(paper.PAPER_RX_OFFSET)
            self.rx_orientation = list(paper.PAPER_RX_ORIENTATION)
            self.uav_mesh = True
            self.bandwidth_hz = paper.PAPER_BANDWIDTH_HZ
        super().__post_init__()
        if self.lookahead and self.uav_mesh:
            raise ValueError("lookahead = true needs uav_mesh = false (a solve places each UAV body at one "
                             "position; forecast positions would see the bodies where the UAVs are now)")
        if self.lookahead_steps < 0 or self.cache_tolerance_m < 0:
            raise ValueError("lookahead_steps and cache_tolerance_m must be >= 0")

    def radio(self) -> RadioConfig:
        names = {f.name for f in dataclasses.fields(RadioConfig)}
        return RadioConfig(**{k: v for k, v in dataclasses.asdict(self).items() if k in names})


class SionnaLink(caviar.Plugin):
    subscribe = [POSITIONS, BEAM_SELECTION, FORECAST]
    publishes = (*LINK_TOPICS, STATE)
    Params = SionnaLinkParams

    def setup(self, ctx):
        p = ctx.params
        self.p = p
        self.radio = RadioScene(p.radio(), seed=ctx.seed, base_dir=ctx.config_dir)
        self.budget = LinkBudget(bandwidth_hz=p.bandwidth_hz, tx_power_w=p.tx_power_w,
                                 interference_dbw=p.interference_dbw)
        self.ue_type: dict[str, str] = {}
        self.positions: dict[str, np.ndarray] = {}
        self.selected: dict[str, int] = {}
        self.forecast: dict[str, list[np.ndarray]] = {}
        self.lookahead = LookaheadTracer(self.radio, p.lookahead_steps, p.cache_tolerance_m) if p.lookahead else None

    def step(self, t, inbox):
        for m in inbox:
            if m.topic == POSITIONS:
                self.ue_type[m.data["UE_Id"]] = m.data["UE_type"]
                self.positions[m.data["UE_Id"]] = read_position(m.data)
            elif m.topic == BEAM_SELECTION:
                self.selected[m.data["UE_Id"]] = int(m.data["beam_pair"])
            elif m.topic == FORECAST:
                self.forecast[m.data["UE_Id"]] = [read_position({"position": q}) for q in m.data["positions"]]
        if not self.positions:
            return
        if self.lookahead is not None:
            links = self.lookahead.links(self.positions, self.forecast)
        else:
            self.radio.place(self.positions)
            links = self.radio.solve()
        n_pairs = self.radio.w_rx.shape[1] * self.radio.n_tx_beams
        for ue, link in links.items():
            yield from link_messages(self.ue_type[ue], ue, link, self.selected.get(ue), n_pairs, self._mbps,
                                     self._snr, self.p.publish_channels)
        yield STATE, "Ready"

    def _snr(self, gain: float) -> float:
        if self.p.protocol == "paper":
            return gain / paper.PAPER_SNR_DIVISOR
        return float(self.budget.sinr(gain))

    def _mbps(self, gain: float) -> float:
        if self.p.protocol == "paper":
            return float(paper.paper_rate_mbps(gain))
        return float(self.budget.throughput_mbps(gain))
