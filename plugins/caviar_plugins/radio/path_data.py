"""Path-level results of a ray-traced link: one receiver's paths of one solve, as
``sionna-link`` publishes them with ``publish_paths = true`` on
``communications.paths.<UE_Id>`` and as ``caviar-core export deepmimo`` reads them.

A :class:`PathData` holds, per path, Sionna's channel coefficient ``a`` at the array
centres (the points a synthetic-array solve traces), the delay, the angles of departure
and arrival, the interaction types and the interaction points, plus the transmitter's
and receiver's positions. ``a`` includes the run's antenna element patterns (each
element has the same pattern) but, as Sionna defines it, not the carrier phase: the
baseband coefficient of a path is ``a·exp(−j2π f τ)`` (:meth:`PathData.baseband`).

The payload is a NumPy ``.npz`` archive (binary; :meth:`PathData.to_bytes`,
:meth:`PathData.from_bytes`), self-contained: it carries the carrier frequency and the
link's ray-tracing settings (scene, arrays, solver flags), so an exporter needs nothing
else from the run.
"""

from __future__ import annotations

import dataclasses
import io
import json
from typing import Any

import numpy as np

# Sionna RT's InteractionType values (sionna.rt.constants), per depth of a path.
NONE, SPECULAR, DIFFUSE, REFRACTION, DIFFRACTION = 0, 1, 2, 4, 8

_ARRAYS = ("a", "tau_s", "theta_t", "phi_t", "theta_r", "phi_r", "interactions", "vertices",
           "tx_position", "rx_position")


@dataclasses.dataclass
class PathData:
    """One receiver's paths of one solve (P paths, D = the solver's ``max_depth``)."""

    a: np.ndarray
    """(P,) complex64: Sionna's path coefficients at the array centres (element patterns
    included, carrier phase not)."""
    tau_s: np.ndarray
    """(P,) float32: delays, s."""
    theta_t: np.ndarray
    """(P,) float32: zenith angles of departure, rad (global frame, 0 = up)."""
    phi_t: np.ndarray
    """(P,) float32: azimuths of departure, rad (from +x toward +y)."""
    theta_r: np.ndarray
    """(P,) float32: zenith angles of arrival, rad (the direction the path comes from)."""
    phi_r: np.ndarray
    """(P,) float32: azimuths of arrival, rad."""
    interactions: np.ndarray
    """(D, P) uint8: Sionna's interaction type at each depth (0 none, 1 specular
    reflection, 2 diffuse reflection, 4 refraction, 8 diffraction); a LOS path has none."""
    vertices: np.ndarray
    """(D, P, 3) float32: the interaction points, m (zeros where there is no interaction)."""
    tx_position: np.ndarray
    """(3,) float64: the transmitter's array centre, m."""
    rx_position: np.ndarray
    """(3,) float64: the receiver's array centre, m (the UE's position plus the antenna offset)."""
    frequency_hz: float
    h_scale: float = 1.0
    """The factor the link applied to its channel H (``normalize = true``: 1/sqrt(mean |H|²);
    otherwise 1). The paths themselves are never scaled."""
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)
    """The link's ray-tracing settings (scene, arrays, solver flags, bandwidth, versions)."""

    @property
    def n_paths(self) -> int:
        return int(self.a.shape[0])

    def baseband(self) -> np.ndarray:
        """(P,) complex128: each path's baseband coefficient a·exp(−j2π f τ), the phase
        computed in float64."""
        phase = -2 * np.pi * self.frequency_hz * self.tau_s.astype(np.float64)
        return self.a.astype(np.complex128) * np.exp(1j * phase)

    def to_bytes(self) -> bytes:
        """The payload: an uncompressed ``.npz`` archive."""
        buf = io.BytesIO()
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        np.savez(buf, **arrays, frequency_hz=np.float64(self.frequency_hz), h_scale=np.float64(self.h_scale),
                 settings=np.array(json.dumps(self.settings, sort_keys=True)))
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, body: bytes | bytearray | memoryview, where: str = "payload") -> "PathData":
        """Reads :meth:`to_bytes`'s payload; ValueError naming ``where`` if it is not one."""
        try:
            with np.load(io.BytesIO(bytes(body)), allow_pickle=False) as z:
                arrays = {name: z[name] for name in _ARRAYS}
                scalars = float(z["frequency_hz"]), float(z["h_scale"]), json.loads(str(z["settings"]))
        except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as e:
            raise ValueError(f"{where}: not a path-data payload ({e})") from None
        p = arrays["a"].shape[0]
        if arrays["vertices"].shape[1:] != (p, 3) or arrays["interactions"].shape[1:] != (p,):
            raise ValueError(f"{where}: inconsistent path-data shapes "
                             f"{ {k: v.shape for k, v in arrays.items()} }")
        return cls(**arrays, frequency_hz=scalars[0], h_scale=scalars[1], settings=scalars[2])


def _unit(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) of zenith ``theta`` and azimuth ``phi``."""
    t, p = theta.astype(np.float64), phi.astype(np.float64)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def receiver_paths(paths: Any, scene: Any, tx_position, rx_positions: np.ndarray,
                   frequency_hz: float) -> list[PathData]:
    """Every receiver's :class:`PathData` of a Sionna RT ``Paths`` object traced with
    ``synthetic_array=True`` from one transmitter, in the scene's receiver order
    (``rx_positions``: their array centres, (N, 3)).

    Sionna's coefficients of a synthetic array are the array centre's times each
    element's phase exp(j2π/λ (k_r·r_m + k_t·r_n)) (k: the unit vectors of departure and
    arrival, r: the element's offset from its array's centre, rotated with the device);
    this undoes that phase for the first element pair to give the centre's coefficient."""
    n_rx = len(rx_positions)
    a = np.array(paths.a[0]) + 1j * np.array(paths.a[1])  # [rx, rx_ant, tx, tx_ant, P]
    n_max = a.shape[-1]
    valid = np.array(paths.valid).reshape(n_rx, n_max)
    per_rx = {name: np.array(getattr(paths, name)).reshape(n_rx, n_max)
              for name in ("tau", "theta_t", "phi_t", "theta_r", "phi_r")}
    inter = np.array(paths.interactions)
    depth = inter.shape[0] if inter.ndim > 1 else 0
    inter = inter.reshape(depth, n_rx, n_max)
    verts = np.array(paths.vertices).reshape(depth, n_rx, n_max, 3)
    wavelength = float(np.asarray(scene.wavelength).ravel()[0])
    rel_tx = np.array(scene.sources(True, True)[2]).T.reshape(-1, 3)  # [tx · tx_array_size, 3], tx-major
    rel_rx = np.array(scene.targets(True, True)[2]).T.reshape(n_rx, -1, 3)  # [rx, rx_array_size, 3]
    k_t = _unit(per_rx["theta_t"], per_rx["phi_t"])
    k_r = _unit(per_rx["theta_r"], per_rx["phi_r"])
    psi = 2 * np.pi / wavelength * (k_r @ rel_rx[:, 0, :, None] + (k_t @ rel_tx[0])[..., None])[..., 0]
    centre = a[:, 0, 0, 0, :] * np.exp(-1j * psi)
    out = []
    for i in range(n_rx):
        v = valid[i]
        out.append(PathData(
            a=centre[i, v].astype(np.complex64), tau_s=per_rx["tau"][i, v].astype(np.float32),
            theta_t=per_rx["theta_t"][i, v].astype(np.float32), phi_t=per_rx["phi_t"][i, v].astype(np.float32),
            theta_r=per_rx["theta_r"][i, v].astype(np.float32), phi_r=per_rx["phi_r"][i, v].astype(np.float32),
            interactions=inter[:, i, v].astype(np.uint8), vertices=verts[:, i, v, :].astype(np.float32),
            tx_position=np.asarray(tx_position, dtype=np.float64).copy(),
            rx_position=np.asarray(rx_positions[i], dtype=np.float64).copy(), frequency_hz=float(frequency_hz)))
    return out
