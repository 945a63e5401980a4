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
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Sequence

import numpy as np

from caviar_plugins.network.cells import Cell, pattern_gain_db
from caviar_plugins.radio.scene import configure_drjit, scene_path

NO_PATH_DB = -250.0
"""The gain of a cell no traced path connects to a UE: far below any noise floor."""


@dataclasses.dataclass(frozen=True)
class TraceSettings:
    scene: str = "empty"
    max_depth: int = 3
    samples_per_src: int = 100_000
    diffraction: bool = True
    refresh_s: float = 1.0
    """Virtual seconds between two traces; in between the gains are held."""

    def __post_init__(self):
        if self.max_depth < 0:
            raise ValueError(f"raytracing.max_depth: expected >= 0, got {self.max_depth}")
        if self.samples_per_src < 1:
            raise ValueError(f"raytracing.samples_per_src: expected >= 1, got {self.samples_per_src}")
        if not self.refresh_s > 0:
            raise ValueError(f"raytracing.refresh_s: expected a positive number of seconds, got {self.refresh_s}")


class SiteTracer:
    """The network's sites in a Sionna RT scene; :meth:`gains_db` traces the UEs."""

    def __init__(self, settings: TraceSettings, cells: Sequence[Cell], seed: int = 0,
                 base_dir: pathlib.Path | None = None):
        configure_drjit()
        import sionna.rt as rt

        self.rt, self.s, self.cells, self.seed = rt, settings, list(cells), int(seed) % (2**31)
        path = scene_path(settings.scene, base_dir)
        self.scene = rt.load_scene(str(path)) if path else rt.load_scene()
        carriers = {c.carrier_hz for c in cells}
        if len(carriers) > 1:
            raise ValueError("raytracing: every cell must share one carrier (one solve per carrier is not "
                             f"supported yet), got {sorted(carriers)}")
        self.scene.frequency = carriers.pop()
        iso = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        self.scene.tx_array, self.scene.rx_array = iso, iso
        self.sites: list[str] = []
        for c in self.cells:
            if c.site not in self.sites:
                self.sites.append(c.site)
                self.scene.add(rt.Transmitter(f"site-{c.site}", position=list(c.position)))
        self.site_of = np.array([self.sites.index(c.site) for c in self.cells])
        self.solver = rt.PathSolver()
        self.receivers: list[str] = []

    def _place(self, ues: np.ndarray) -> None:
        n = len(ues)
        while len(self.receivers) < n:
            name = f"ue-{len(self.receivers)}"
            self.scene.add(self.rt.Receiver(name, position=[0.0, 0.0, 0.0]))
            self.receivers.append(name)
        while len(self.receivers) > n:
            self.scene.remove(self.receivers.pop())
        for name, p in zip(self.receivers, ues, strict=True):
            self.scene.receivers[name].position = [float(v) for v in p]

    def gains_db(self, ues: np.ndarray) -> np.ndarray:
        """Path gain (dB) of every cell toward every UE, its sector pattern included:
        [n_ue, n_cell]; :data:`NO_PATH_DB` where no path reaches. One solve for every site."""
        n_ue = len(ues)
        if n_ue == 0:
            return np.zeros((0, len(self.cells)))
        self._place(ues)
        s = self.s
        paths = self.solver(self.scene, max_depth=s.max_depth, samples_per_src=s.samples_per_src,
                            synthetic_array=True, los=True, specular_reflection=True, diffuse_reflection=False,
                            refraction=False, diffraction=s.diffraction, seed=self.seed)
        a_re, a_im = (np.array(x) for x in paths.a)  # [rx, rx_ant, tx, tx_ant, paths]
        power = (a_re ** 2 + a_im ** 2)[:, 0, :, 0, :]  # [rx, tx, paths]
        valid = np.array(paths.valid).reshape(power.shape)
        theta = np.array(paths.theta_t).reshape(power.shape)  # zenith of departure
        phi = np.array(paths.phi_t).reshape(power.shape)  # azimuth of departure
        power = np.where(valid, power, 0.0)
        out = np.empty((n_ue, len(self.cells)))
        for k, cell in enumerate(self.cells):
            site = self.site_of[k]
            g = 10 ** (pattern_gain_db(cell, np.degrees(theta[:, site]), np.degrees(phi[:, site])) / 10)
            total = (power[:, site] * g).sum(axis=-1)
            out[:, k] = 10 * np.log10(np.maximum(total, 10 ** (NO_PATH_DB / 10)))
        return out
