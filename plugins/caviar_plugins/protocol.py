"""The ``protocol`` switch shared by the plugins whose behaviour differs between this
project's model and the 2023 CAVIAR code (see docs/paper-protocol.md).

* ``physical`` (default): path loss and a link budget, the Kronecker DFT codebook at
  0.5 λ, the full route, hover on detection.
* ``paper``: what the 2023 code did, so that the paper's tables reproduce: unit-energy
  channels with the line-of-sight path dropped, a 64-point DFT over the flat element
  index at 5.714 λ spacing, R = 40 MHz · log2(1 + |g|² / 3248.11), the route to
  waypoint 4, hovers deferred to the next waypoint, byte-level image loss.

The paper's constants live here, next to the switch, with the code they come from.
"""

from __future__ import annotations

import numpy as np

from caviar_plugins.constants import BOLTZMANN

PROTOCOLS = ("physical", "paper")


def check_protocol(value: str, key: str = "protocol") -> str:
    """``value`` if it names a protocol, else a ValueError that names the key."""
    if value not in PROTOCOLS:
        raise ValueError(f"{key}: expected one of {', '.join(repr(p) for p in PROTOCOLS)}, got {value!r}")
    return value


# --- Link (execute_run.py, calc_time.py, mimo_channels.py at 45bbcbf) -------------------
PAPER_SPACING = 0.5 * 40e9 / 3.5e9
"""Element spacing in wavelengths: the arrays were built at Sionna's default 3.5 GHz with
0.5 λ and used at 40 GHz, i.e. 5.714 λ (bug B1, kept)."""
PAPER_RX_OFFSET = (0.35, 0.069, -8.23)
"""Receiver relative to the UAV position: 1 m above ground at z_NED = 128 (B6, kept)."""
PAPER_RX_ORIENTATION = (-0.523599, 0.0, 0.0)
PAPER_BANDWIDTH_HZ = 40e6
PAPER_NOISE_W = BOLTZMANN * 290.0 * PAPER_BANDWIDTH_HZ * (1 + 298.15 / 290.0)
"""k_B·290·B·NF with NF = 1 + 298.15/290 (3.07 dB): 3.248e-13 W."""
PAPER_INTERFERENCE_W = 10 ** (100 / 10)
"""``interference_power_dBW = 100`` (sign error in the 2023 code)."""
PAPER_SNR_DIVISOR = (PAPER_NOISE_W * 1e3) * (PAPER_INTERFERENCE_W * 1e3)
"""SNR = |g|² / (N_mW · I_mW) = |g|² / 3248.11 (a product of powers: B4, kept)."""
PAPER_LINK = {"spacing": PAPER_SPACING, "raytracing.los": False, "raytracing.diffuse_reflection": False,
              "raytracing.refraction": False, "raytracing.specular_reflection": True, "raytracing.diffraction": True,
              "codebook": "flat-dft", "normalize": True,
              "antenna_offset": list(PAPER_RX_OFFSET), "rx_orientation": list(PAPER_RX_ORIENTATION),
              "uav_mesh": True, "bandwidth_hz": PAPER_BANDWIDTH_HZ}
"""What ``protocol = "paper"`` sets of sionna-link's parameters: the 2023 code's link (LOS
path dropped, unit-energy H, no refraction or diffuse reflection, 5.714 λ spacing, the flat
64-point DFT, Rx 8.23 m below the UAV, 40 MHz)."""


def paper_rate_mbps(gain) -> np.ndarray:
    """The 2023 code's throughput in Mbit/s for a beam-pair gain |g|² of the unit-energy
    channel and unnormalised codebooks: 40 MHz · log2(1 + |g|² / 3248.11); at most
    176.18 Mbit/s (|g|² ≤ 4 · 64 · 256 = 65 536), no Tx power, no distance."""
    return PAPER_BANDWIDTH_HZ * np.log2(1 + np.asarray(gain, dtype=float) / PAPER_SNR_DIVISOR) / 1e6


# --- Flight and mission (caviar_integration.py, caviar_tools.py at 45bbcbf) ---------------
PAPER_LAST_WAYPOINT = 4
"""The mission ends when the UAV leaves waypoint 4 (end rule ``len - 5`` on 10 rows)."""
PAPER_TAKEOFF_S = 8.5
"""Mission clock at the first stepped move from waypoint 0: AirSim's takeoff (3 m at
0.5 m/s), a 1 s real-time sleep and the descent back to waypoint 0. Not recorded in
2023; an estimate (range 7-10 s) from AirSim's takeoff."""
PAPER_ARRIVAL_TOLERANCE = (0.5, 0.5, 0.6)
"""|Δx|, |Δy|, |Δz| within which a waypoint counts as reached (caviar_tools.py)."""
PAPER_ACCELERATION = 5.0
"""m/s²: stop-and-go legs take L / v + 1 s at v = 5 m/s (AirSim's speed set-point)."""
PAPER_PERSONS_SCENE = ((-264.00, 176.16), (-153.66, 128.93), (-134.66, 118.48), (-113.66, 106.93),
                       (-46.66, 70.08))
"""The paper's 5 persons, at SAR path rows 1-5 (scene frame); rows 1-4 are on the flown part."""

# --- Image loss (caviar_integration.py applyFilter at 45bbcbf) ---------------------------
PAPER_LOSS = ((60.0, 0.01), (30.0, 0.25), (-np.inf, 0.50))
"""(throughput above which, loss rate): > 60 Mbit/s 1 % (the 0.9 Gbit/s typo makes the
table's 90 Mbit/s bound void), 30-60 25 %, ≤ 30 50 %."""


def zero_bytes(image: np.ndarray, rate: float, rng: np.random.Generator) -> np.ndarray:
    """The 2023 code's degradation: exactly ⌊N·rate⌋ randomly chosen bytes (channel
    samples) of the image set to 0, without replacement."""
    flat = np.ascontiguousarray(image).reshape(-1).copy()
    lost = rng.choice(flat.size, size=int(flat.size * rate), replace=False)
    flat[lost] = 0
    return flat.reshape(image.shape)
