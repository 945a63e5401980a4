"""A free-space communications model: the quickstart's stand-in for ray tracing.

Friis path gain from the rooftop transmitter to every UE, ideal beamforming gains
of the Tx and Rx arrays (N_tx · N_rx), and the paper's link budget. Cheap and
exact where the line of sight is clear; the Sionna RT module replaces it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import caviar
from caviar_plugins.radio.link_budget import LinkBudget, friis_path_gain
from caviar_plugins.radio.link_report import db
from caviar_plugins.schema import LINK, POSITIONS, STATE, THROUGHPUT, read_position, throughput_payload


class FreeSpaceLink(caviar.Plugin):
    subscribe = [POSITIONS]
    publishes = (THROUGHPUT, STATE, LINK)

    stateless = True  # each step from its inbox alone: a resumed run needs only setup

    @dataclasses.dataclass
    class Params:
        tx_position: list[float] = dataclasses.field(default_factory=lambda: [-154.0, 64.0, 120.0])
        frequency_hz: float = 40e9
        tx_array: list[int] = dataclasses.field(default_factory=lambda: [8, 8])
        rx_array: list[int] = dataclasses.field(default_factory=lambda: [2, 2])
        bandwidth_hz: float = 40e6
        tx_power_w: float = 0.5
        interference_dbw: float = -130.0
        publish_link: bool = False
        """Also publish ``communications.link`` per UE (line of sight, one path): its Friis
        ``path_gain_db``, ``pair_gain_db`` (with both arrays' gain) and ``snr_db``, what a
        network simulator (``ns3-network``) takes its losses from."""

        def __post_init__(self):
            if len(self.tx_position) != 3:
                raise ValueError(f"tx_position: expected [x, y, z], got {self.tx_position}")
            if not self.frequency_hz > 0:
                raise ValueError(f"frequency_hz: expected a positive frequency in Hz, got {self.frequency_hz}")

    def setup(self, ctx):
        p = ctx.params
        self.p = p
        self.tx = np.asarray(p.tx_position, dtype=float)
        self.array_gain = float(np.prod(p.tx_array) * np.prod(p.rx_array))
        self.budget = LinkBudget(bandwidth_hz=p.bandwidth_hz, tx_power_w=p.tx_power_w,
                                 interference_dbw=p.interference_dbw)

    def step(self, t, inbox):
        latest = {}
        for m in inbox.on(POSITIONS):
            latest[(m.data["UE_type"], m.data["UE_Id"])] = read_position(m.data)
        for (ue_type, ue_id), pos in latest.items():
            # Plain IEEE arithmetic: np.linalg.norm goes through BLAS, whose kernels
            # (chosen per CPU) round differently, so recorded runs would differ by machine.
            dx, dy, dz = (float(v) for v in pos - self.tx)
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            gain = friis_path_gain(d, self.p.frequency_hz) * self.array_gain
            mbps = float(self.budget.throughput_mbps(gain))
            yield THROUGHPUT, throughput_payload(ue_type, ue_id, mbps)
            if self.p.publish_link:
                path_gain = gain / self.array_gain
                yield LINK, {"UE_type": ue_type, "UE_Id": ue_id, "los": True, "n_paths": 1, "best_pair": 0,
                             "pair": 0, "selected": False, "path_gain_db": db(float(path_gain)),
                             "pair_gain_db": db(float(gain)), "snr_db": db(float(self.budget.sinr(gain))),
                             "best_throughput": mbps}
        if latest:
            yield STATE, "Ready"
