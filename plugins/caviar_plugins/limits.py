"""Bounds on what one setting may ask of the machine, checked before anything runs.

A setting that multiplies the work of a step or the memory it takes (a LiDAR's azimuth step,
its spin rate, the UEs a layout drops in every sector, an FTP arrival rate, the rays a ray
tracer shoots) has a bound here, a few times above any real sensor or any 3GPP evaluation,
that keeps one step within minutes and a few GB on the development machine (2 cores, 8 GB).
Past it the parameter check fails, naming the key, the amount and the bound; a module's
``allow_large = true`` (a key of its ``params``) lifts its bounds for whoever knows that their
machine can do it. ``docs/guide/resources.md`` lists them.
"""

from __future__ import annotations

ALLOW = "allow_large"
"""The parameter that lifts a module's bounds (``[modules.NAME.params] allow_large = true``)."""

LIDAR_RAYS_PER_SWEEP = 5_000_000
"""Rays of one LiDAR sweep (channels × 360 / horizontal_resolution_deg): about 100 bytes each
while a sweep is cast, so 0.5 GB. The largest sensors sold (128 channels at 0.1°) fire 460,800."""
LIDAR_RATE_HZ = 100.0
"""Sweeps per second of virtual time (real spinning LiDARs: 5 to 20 Hz): a step of Ts seconds
casts rate_hz × Ts sweeps, one after the other."""
LIDAR_RAYS_PER_S = 50_000_000
"""Rays per second of virtual time, every LiDAR together (the default sensor: 576,000): a step
of Ts seconds casts this × Ts rays."""
DROPPED_UES = 10_000
"""UEs a radio network's layout drops (ues_per_sector × sectors × sites): every one has a
channel to every cell and a column in the link level at every slot. TR 38.901's calibration
drops 10 a sector, 570 in all."""
FTP_ARRIVAL_RATE_HZ = 1_000.0
"""FTP files arriving per second per UE and direction (3GPP evaluations: about 0.1 to 10)."""
ARRAY_ELEMENTS = 1_024
"""Antenna ports of one cell's panel (rows × columns; 64T64R massive MIMO has 64)."""
SAMPLES_PER_SOURCE = 100_000_000
"""Rays a ray tracer shoots from each source (Sionna RT's default: 1,000,000)."""
MAP_CELLS = 25_000_000
"""Cells of a radio map (a 5,000 × 5,000 grid)."""


def bounded(key: str, amount: float, bound: float, what: str, allow: bool, unit: str = "") -> None:
    """A ``ValueError`` naming ``key`` when ``amount`` (``what`` the setting asks for) is over
    ``bound`` and ``allow`` (the module's ``allow_large``) is false."""
    if allow or amount <= bound:
        return
    unit = f" {unit}" if unit else ""
    raise ValueError(f"{key}: {what} is {_number(amount)}{unit}, more than the bound of {_number(bound)}{unit} "
                     f"(caviar_plugins.limits: one step's work and memory within a workstation's); set {ALLOW} = "
                     f"true in this module's params to run it anyway")


def _number(x: float) -> str:
    if x >= 1e12:
        return f"{x:.3g}"
    return f"{x:,.0f}" if float(x).is_integer() else f"{x:,.6g}"
