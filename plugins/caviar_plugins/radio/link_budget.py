"""Link budget of the paper's communications module.

SINR = P_tx · G / (N + I) with N = k_B · (T + T_e) · B, and throughput from
Shannon's capacity C = B · log2(1 + SINR). Defaults are the paper's: 40 MHz,
0.5 W, T = 290 K, T_e = 298.15 K, I = -130 dBW.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from caviar_plugins.constants import BOLTZMANN, SPEED_OF_LIGHT


@dataclasses.dataclass(frozen=True)
class LinkBudget:
    bandwidth_hz: float = 40e6
    tx_power_w: float = 0.5
    noise_temperature_k: float = 290.0
    receiver_temperature_k: float = 298.15
    interference_dbw: float = -130.0

    @property
    def noise_w(self) -> float:
        return BOLTZMANN * (self.noise_temperature_k + self.receiver_temperature_k) * self.bandwidth_hz

    def sinr(self, gain) -> np.ndarray:
        """SINR (linear) for a total channel power gain (path gain × beamforming gains)."""
        interference = 10 ** (self.interference_dbw / 10)
        return self.tx_power_w * np.asarray(gain, dtype=float) / (self.noise_w + interference)

    def throughput_mbps(self, gain) -> np.ndarray:
        return self.bandwidth_hz * np.log2(1 + self.sinr(gain)) / 1e6


def friis_path_gain(distance_m, frequency_hz: float) -> np.ndarray:
    """Free-space path gain (λ / 4πd)² between isotropic antennas."""
    lam = SPEED_OF_LIGHT / frequency_hz
    return (lam / (4 * np.pi * np.asarray(distance_m, dtype=float))) ** 2
