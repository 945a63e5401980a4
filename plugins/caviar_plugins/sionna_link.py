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
from caviar_plugins.linkbudget import LinkBudget
from caviar_plugins.radio import RadioConfig, RadioScene

POSITIONS = "3D.mobility.positions"
SELECTION = "ai.beam.selection"
THROUGHPUT = "communications.throughput"
LINK = "communications.link"
STATE = "communications.state"


@dataclasses.dataclass
class SionnaLinkParams(RadioConfig):
    bandwidth_hz: float = 40e6
    tx_power_w: float = 0.5
    interference_dbw: float = -130.0
    publish_channels: bool = True
    """Publish H and the beam gains as binary payloads."""

    def radio(self) -> RadioConfig:
        names = {f.name for f in dataclasses.fields(RadioConfig)}
        return RadioConfig(**{k: v for k, v in dataclasses.asdict(self).items() if k in names})


class SionnaLink(caviar.Plugin):
    subscribe = [POSITIONS, SELECTION]
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

    def step(self, t, inbox):
        for m in inbox:
            if m.topic == POSITIONS:
                d = m.data
                self.ue_type[d["UE_Id"]] = d["UE_type"]
                pos = d["position"]
                self.positions[d["UE_Id"]] = np.array([pos["x"], pos["y"], pos["z"]], dtype=float)
            elif m.topic == SELECTION:
                self.selected[m.data["UE_Id"]] = int(m.data["beam_pair"])
        if not self.positions:
            return
        self.radio.place(self.positions)
        links = self.radio.solve()
        n_pairs = self.radio.w_rx.shape[1] * self.radio.n_tx_beams
        for ue, link in links.items():
            pair = self.selected.get(ue, link.best_pair)
            if not 0 <= pair < n_pairs:
                raise ValueError(f"beam pair {pair} for {ue} is outside 0..{n_pairs - 1}")
            gain = float(link.gains.flat[pair])
            ue_type = self.ue_type[ue]
            yield THROUGHPUT, {"UE_type": ue_type, "UE_Id": ue, "throughput": float(self.budget.throughput_mbps(gain))}
            yield LINK, {
                "UE_type": ue_type, "UE_Id": ue, "los": link.los, "n_paths": link.n_paths,
                "best_pair": link.best_pair, "pair": pair, "selected": ue in self.selected,
                "path_gain_db": _db(link.path_gain), "snr_db": _db(float(self.budget.sinr(gain))),
                "best_throughput": float(self.budget.throughput_mbps(link.gains.max())),
            }
            if self.p.publish_channels:
                yield f"communications.channel.{ue}", link.h.astype(np.complex64)
                yield f"communications.beam_gains.{ue}", link.gains.astype(np.float32)
        yield STATE, "Ready"


def _db(x: float) -> float:
    return float(10 * np.log10(x)) if x > 0 else -400.0
