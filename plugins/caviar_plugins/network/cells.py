"""Sites, sectors and what a UE measures of them: received power, RSRP and SINR.

A **site** is a mast at one position; each of its **sectors** is a cell: an antenna
panel pointing at an azimuth (3GPP TR 38.901 §7.3 element pattern, 65° half-power
beamwidths, 8 dBi, 30 dB front-to-back) with an array of ``rows × cols`` elements whose
beamforming gain toward the UE is ``10·log10(rows·cols)``, a transmit power, a carrier
and a bandwidth. Cells on the same carrier interfere with each other.

Received power, per UE ``u`` and cell ``c``: ``P_rx = P_tx + A(c) + G(c, u)`` (dB), ``A``
the array gain and ``G`` the channel gain with the sector pattern: free space
(:func:`line_of_sight_gain_db`) or the ray tracer's paths, each weighted by the pattern at
its departure direction (:mod:`caviar_plugins.network.raytraced`). ``RSRP = P_rx − 10·log10(12·N_PRB)``
(power per resource element). SINR of UE ``u`` served by ``s``::

    SINR = P_rx(s) / (N + Σ_{c ≠ s, same carrier} load(c) · P_rx(c) / A(c))

with ``N = k·T·B·NF``, ``load`` 1 for every interfering cell (``full-buffer``) or 1 only
for cells that scheduled someone in the slot (``scheduled``), and ``A(c)`` the array gain
of cell ``c``: its data beams point at its own UEs, and the array factor averaged over
directions is 1, so an interferer reaches the UE with its element gain only (RSRP is
measured on beam-swept reference signals and keeps the array gain). With ``beams`` the
network uses the beams themselves instead (:mod:`caviar_plugins.network.beams`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

from caviar_plugins.constants import BOLTZMANN, SPEED_OF_LIGHT

REFERENCE_TEMPERATURE_K = 290.0
# TR 38.901 Table 7.3-1: the sector element pattern.
ELEMENT_GAIN_DBI = 8.0
HALF_POWER_BEAMWIDTH_DEG = 65.0
FRONT_TO_BACK_DB = 30.0
SIDE_LOBE_DB = 30.0


@dataclasses.dataclass(frozen=True)
class Column:
    """A vertical column of ``elements`` sector elements, ``spacing_wavelengths`` apart,
    fed with one port through the virtualisation weights of TR 36.897 §5.2.2 (option
    1-A) that steer it to ``electrical_tilt_deg`` below the horizon: TR 38.901 Table 7.8-1's
    "config 1" for UMa and UMi, 10 elements tilted 12° (a zenith of 102°). Spaced 0.5 λ as
    in QuaDRiGa's 38.901 calibration; at 0.8 λ the UMa 6 GHz coupling loss leaves the 3GPP
    companies' band (median 123.5 dB against their 118.1–123.1 dB, measured here)."""

    elements: int = 10
    spacing_wavelengths: float = 0.5
    electrical_tilt_deg: float = 12.0

    def __post_init__(self):
        if isinstance(self.elements, bool) or not isinstance(self.elements, int) or self.elements < 1:
            raise ValueError(f"elements: expected a whole number of elements >= 1, got {self.elements!r}")
        if not 0 < self.spacing_wavelengths <= 4:
            raise ValueError(f"spacing_wavelengths: expected a spacing in (0, 4] wavelengths, "
                             f"got {self.spacing_wavelengths!r}")
        if not -90 <= self.electrical_tilt_deg <= 90:
            raise ValueError(f"electrical_tilt_deg: expected a tilt in [-90, 90] degrees below the horizon, "
                             f"got {self.electrical_tilt_deg!r}")

    def gain_db(self, theta_deg: np.ndarray) -> np.ndarray:
        """The column's array gain (dB, 10·log10(M) at the tilt) toward zenith angles
        ``theta_deg`` (90° at the horizon) in the panel's frame:
        ``|Σ_m w_m·a_m(θ)|²`` with ``a_m = exp(j2π(m−1)d·cos θ)`` and
        ``w_m = exp(−j2π(m−1)d·cos θ_tilt)/√M``, summed in closed form."""
        m = self.elements
        psi = 2 * np.pi * self.spacing_wavelengths * (
            np.cos(np.radians(np.asarray(theta_deg, dtype=float)))
            - np.cos(np.radians(90.0 + self.electrical_tilt_deg)))
        half = psi / 2
        small = np.abs(np.sin(half)) < 1e-9
        ratio = np.where(small, float(m), np.sin(m * half) ** 2 / np.where(small, 1.0, m * np.sin(half) ** 2))
        return 10 * np.log10(np.maximum(ratio, 1e-30))


@dataclasses.dataclass(frozen=True)
class Cell:
    """One sector of a site: a cell."""

    name: str  # "SITE/k", k the sector's index at its site
    site: str
    index: int  # position in the list of all cells
    position: tuple[float, float, float]
    azimuth_deg: float  # boresight, counter-clockwise from +x (east)
    downtilt_deg: float
    tx_power_dbm: float
    carrier_hz: float
    bandwidth_hz: float
    array: tuple[int, int]
    column: Column | None = None
    """The elements behind each port (TR 38.901 Table 7.8-1 "config 1": a column of 10
    elements with an electrical tilt): their array factor is part of the cell's pattern,
    toward every UE, not a beam to one."""

    @property
    def array_gain_db(self) -> float:
        return 10 * math.log10(self.array[0] * self.array[1])


def _fail(key: str, message: str) -> ValueError:
    """A ValueError the plugin host reports at ``modules.NAME.params.KEY``."""
    return ValueError(f"{key}: {message}")


def _number(table: Mapping[str, Any], key: str, where: str, default: float | None = None,
            positive: bool = False) -> float:
    """``table[key]``, else the network-wide ``default``; an error names the key the value came
    from (``sites.2.bandwidth_hz``, or the network's ``bandwidth_hz``)."""
    value = table.get(key, default)
    at = f"{where}.{key}" if key in table else key
    if value is None:
        raise _fail(f"{where}.{key}", "this required key is missing")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _fail(at, f"expected a number, got {value!r}")
    if positive and not value > 0:
        raise _fail(at, f"expected a positive number, got {value!r}")
    return float(value)


SITE_KEYS = {"name", "position", "azimuths_deg", "downtilt_deg", "tx_power_dbm", "carrier_hz",
             "bandwidth_hz", "array"}


def parse_sites(sites: Sequence[Mapping[str, Any]], defaults: Mapping[str, Any]) -> list[Cell]:
    """The cells of ``sites`` (``[[...params.sites]]`` tables), in order, checked.

    ``defaults`` holds the network-wide ``tx_power_dbm``, ``carrier_hz``,
    ``bandwidth_hz`` and ``array`` a site may override. Errors name the key
    (``sites.2.array``) and say what was expected.
    """
    if not sites:
        raise _fail("sites", "expected at least one [[...params.sites]] table")
    cells: list[Cell] = []
    seen: set[str] = set()
    for i, site in enumerate(sites):
        where = f"sites.{i}"
        if not isinstance(site, Mapping):
            raise _fail(where, f"expected a table, got {site!r}")
        unknown = sorted(set(site) - SITE_KEYS)
        if unknown:
            raise _fail(f"{where}.{unknown[0]}", f"unknown key, expected one of {sorted(SITE_KEYS)}")
        name = site.get("name")
        if not isinstance(name, str) or not name or "/" in name:
            raise _fail(f"{where}.name", f"expected a site name without '/', got {name!r}")
        if name in seen:
            raise _fail(f"{where}.name", f"site '{name}' is declared twice (site names must be unique)")
        seen.add(name)
        pos = site.get("position")
        if not (isinstance(pos, list) and len(pos) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pos)):
            raise _fail(f"{where}.position", f"expected [x, y, z] in metres, got {pos!r}")
        azimuths = site.get("azimuths_deg", [0.0, 120.0, 240.0])
        if not (isinstance(azimuths, list) and azimuths
                and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in azimuths)):
            raise _fail(f"{where}.azimuths_deg", f"expected a list of sector azimuths in degrees, got {azimuths!r}")
        array = site.get("array", defaults.get("array"))
        if not (isinstance(array, list) and len(array) == 2
                and all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in array)):
            raise _fail(f"{where}.array" if "array" in site else "array",
                        f"every sector needs an antenna array [rows, cols] of elements >= 1, got {array!r}")
        power = _number(site, "tx_power_dbm", where, defaults.get("tx_power_dbm"))
        carrier = _number(site, "carrier_hz", where, defaults.get("carrier_hz"), positive=True)
        bandwidth = _number(site, "bandwidth_hz", where, defaults.get("bandwidth_hz"), positive=True)
        tilt = _number(site, "downtilt_deg", where, 0.0)
        for k, az in enumerate(azimuths):
            cells.append(Cell(name=f"{name}/{k}", site=name, index=len(cells),
                              position=(float(pos[0]), float(pos[1]), float(pos[2])),
                              azimuth_deg=float(az), downtilt_deg=tilt, tx_power_dbm=power,
                              carrier_hz=carrier, bandwidth_hz=bandwidth,
                              array=(int(array[0]), int(array[1]))))
    return cells


def local_angles_deg(theta_deg: np.ndarray, phi_deg: np.ndarray, bearing_deg: float, downtilt_deg: float,
                     slant_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The zenith ``θ'`` and azimuth ``φ'`` (degrees, ``φ'`` in (−180, 180]) in an antenna's
    local frame of directions given as zenith ``theta_deg`` and azimuth ``phi_deg`` in the
    scene frame: TR 38.901 eq. 7.1-7 and 7.1-8, the frame rotated by ``R = Rz(α)·Ry(β)·Rx(γ)``
    (bearing ``α`` counter-clockwise from +x, downtilt ``β`` positive down, slant ``γ``).

    The two equations are the components of ``R⁻¹·ρ̂`` (``ρ̂`` the unit direction)::

        z' = cos β cos γ cos θ + (sin β cos γ cos(φ−α) − sin γ sin(φ−α)) sin θ     (7.1-7: cos θ')
        x' = cos β sin θ cos(φ−α) − sin β cos θ                                    (7.1-8: Re)
        y' = cos β sin γ cos θ + (sin β sin γ cos(φ−α) + cos γ sin(φ−α)) sin θ     (7.1-8: Im)

    and ``θ' = atan2(√(x'² + y'²), z')`` (``arccos z'``, without its loss of precision near
    the poles), ``φ' = atan2(y', x')``. Without tilt and slant the rotation is about z alone:
    ``θ' = θ`` and ``φ' = φ − α``, returned as such (bit for bit what they were)."""
    theta = np.asarray(theta_deg, dtype=float)
    phi = np.asarray(phi_deg, dtype=float)
    if downtilt_deg == 0.0 and slant_deg == 0.0:
        return theta, (phi - bearing_deg + 180.0) % 360.0 - 180.0
    th, dphi = np.radians(theta), np.radians(phi - bearing_deg)
    b, g = math.radians(downtilt_deg), math.radians(slant_deg)
    st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(dphi), np.cos(dphi)
    z = math.cos(b) * math.cos(g) * ct + (math.sin(b) * math.cos(g) * cp - math.sin(g) * sp) * st
    x = math.cos(b) * st * cp - math.sin(b) * ct
    y = math.cos(b) * math.sin(g) * ct + (math.sin(b) * math.sin(g) * cp + math.cos(g) * sp) * st
    return np.degrees(np.arctan2(np.hypot(x, y), z)), np.degrees(np.arctan2(y, x))


def pattern_gain_db(cell: Cell, theta_deg: np.ndarray, phi_deg: np.ndarray) -> np.ndarray:
    """TR 38.901 sector element gain (dBi) of ``cell`` toward directions of departure given
    as zenith ``theta_deg`` (90° at the horizon) and azimuth ``phi_deg`` (from +x, counter-
    clockwise), in the scene frame; the panel points at the cell's azimuth, tilted down
    (mechanically). Table 7.3-1's pattern is taken at the panel's local angles, the exact
    rotation of eq. 7.1-7 and 7.1-8 (:func:`local_angles_deg`: bearing the azimuth, downtilt
    the tilt, no slant), the one the beams' phases use (``beams.panel_frequencies``). With a
    :class:`Column`, its array gain (at the local zenith) is added."""
    theta, phi = local_angles_deg(theta_deg, phi_deg, cell.azimuth_deg, cell.downtilt_deg)
    a_h = -np.minimum(12 * (phi / HALF_POWER_BEAMWIDTH_DEG) ** 2, FRONT_TO_BACK_DB)
    a_v = -np.minimum(12 * ((theta - 90.0) / HALF_POWER_BEAMWIDTH_DEG) ** 2, SIDE_LOBE_DB)
    gain = ELEMENT_GAIN_DBI - np.minimum(-(a_h + a_v), FRONT_TO_BACK_DB)
    if cell.column is not None:
        gain = gain + cell.column.gain_db(theta)
    return gain


def element_gain_db(cells: Sequence[Cell], ues: np.ndarray) -> np.ndarray:
    """The sector element gain (dBi) of every cell along the straight line to every UE:
    [n_ue, n_cell]."""
    out = np.empty((len(ues), len(cells)))
    for k, c in enumerate(cells):
        d = ues - np.asarray(c.position)
        phi = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        theta = np.degrees(np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]))
        out[:, k] = pattern_gain_db(c, theta, phi)
    return out


def free_space_gain_db(cells: Sequence[Cell], ues: np.ndarray) -> np.ndarray:
    """Friis path gain 20·log10(λ / 4πd) of every cell toward every UE: [n_ue, n_cell]."""
    pos = np.array([c.position for c in cells])
    d = np.sqrt(((ues[:, None, :] - pos[None, :, :]) ** 2).sum(axis=-1))
    lam = SPEED_OF_LIGHT / np.array([c.carrier_hz for c in cells])[None, :]
    return 20 * np.log10(lam / (4 * np.pi * np.maximum(d, 1e-3)))


def line_of_sight_gain_db(cells: Sequence[Cell], ues: np.ndarray) -> np.ndarray:
    """The free-space channel: Friis and the sector pattern along the straight line."""
    return free_space_gain_db(cells, ues) + element_gain_db(cells, ues)


def noise_dbm(bandwidth_hz: np.ndarray | float, noise_figure_db: float) -> np.ndarray:
    """Thermal noise k·T·B·NF in dBm."""
    return 10 * np.log10(BOLTZMANN * REFERENCE_TEMPERATURE_K * np.asarray(bandwidth_hz) * 1e3) + noise_figure_db


def rx_power_dbm(cells: Sequence[Cell], channel_gain_db: np.ndarray) -> np.ndarray:
    """Received power (dBm) from every cell at every UE, [n_ue, n_cell, ...], from the
    channel gains (path gain and sector pattern, [n_ue, n_cell, ...]: wideband or per
    subband) and the cells' power and array."""
    gain = np.asarray(channel_gain_db, dtype=float)
    tx = np.array([c.tx_power_dbm + c.array_gain_db for c in cells])
    return tx.reshape(1, -1, *(1,) * (gain.ndim - 2)) + gain


def rsrp_dbm(cells: Sequence[Cell], rx_dbm: np.ndarray, num_prb: Sequence[int]) -> np.ndarray:
    """Reference signal received power: the received power per resource element."""
    return rx_dbm - 10 * np.log10(12 * np.asarray(num_prb, dtype=float))[None, :]


def sinr_db(cells: Sequence[Cell], rx_dbm: np.ndarray, serving: np.ndarray, noise_figure_db: float,
            load: np.ndarray | None = None) -> np.ndarray:
    """SINR (dB) of every UE on its serving cell ``serving[u]`` (index; -1: none, NaN
    out), the other cells on its carrier interfering with weight ``load[c]`` (default 1:
    full buffer). ``rx_dbm``: [n_ue, n_cell] wideband, or [n_ue, n_cell, ...] per
    frequency (subband), each entry the power the whole band would get at that gain:
    the result is [n_ue] or [n_ue, ...]."""
    rx_dbm = np.asarray(rx_dbm, dtype=float)
    n_ue, n_cell = rx_dbm.shape[:2]
    out = np.full((n_ue, *rx_dbm.shape[2:]), np.nan)
    if n_ue == 0:
        return out
    carrier = np.array([c.carrier_hz for c in cells])
    bandwidth = np.array([c.bandwidth_hz for c in cells])
    load = np.ones(n_cell) if load is None else np.asarray(load, dtype=float)
    rx_mw = 10 ** (rx_dbm / 10)
    # Interferers without their array gain (their beams serve their own UEs).
    load = load / 10 ** (np.array([c.array_gain_db for c in cells]) / 10)
    extra = (1,) * (rx_dbm.ndim - 2)
    # Every UE at once: the other cells on its serving cell's carrier, weighted by their load.
    served = np.asarray(serving) >= 0
    s = np.maximum(np.asarray(serving), 0)
    co = (carrier[None, :] == carrier[s][:, None]) & (np.arange(n_cell)[None, :] != s[:, None])  # [ue, cell]
    interference = (rx_mw * (co * load[None, :]).reshape(n_ue, n_cell, *extra)).sum(axis=1)
    noise = (10 ** (noise_dbm(bandwidth[s], noise_figure_db) / 10)).reshape(n_ue, *extra)
    with np.errstate(divide="ignore", invalid="ignore"):  # (the SIR of a UE alone on its carrier: +inf)
        sinr = 10 * np.log10(rx_mw[np.arange(n_ue), s] / (noise + interference))
    out[served] = sinr[served]
    return out
