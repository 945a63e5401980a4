"""Best-server SINR map of the area from Sionna RT's radio-map solver, per cell and combined.

Every cell is one transmitter with Sionna's ``tr38901`` element (the TR 38.901 sector
pattern, 8 dBi, 65°, 30 dB, the model :mod:`~caviar_plugins.network.cells` computes),
pointed at its azimuth and tilted down; one call of Sionna's ``RadioMapSolver``
(:func:`~caviar_plugins.rt.solver.radio_map`)
gives every cell's path gain on a horizontal grid at UE height. From it, per grid cell:
the RSRP of every cell, the best server, and the SINR on it with the other co-channel
cells interfering (the same :func:`~caviar_plugins.network.cells.sinr_db` the UEs get).

:func:`save` writes it (arrays, a figure, and the SINR as an image layer for the browser
view); :func:`layer_message` is the ``view.*`` payload that draws that layer.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, ClassVar, Sequence

import numpy as np

from caviar_plugins.network.cells import Cell, rsrp_dbm, rx_power_dbm, sinr_db
from caviar_plugins.rt.scene import AntennaArray, Emitter, build_scene
from caviar_plugins.rt.settings import TraceSettings
from caviar_plugins.rt.solver import radio_map

NO_SIGNAL_DB = -250.0
SINR_RANGE_DB = (-10.0, 40.0)
"""The colour scale of the SINR figure and layer (viridis)."""
LAYER_FILE = "radio-map-layer.png"


MAP_RAYS = TraceSettings(samples_per_src=200_000, max_depth=2, diffuse_reflection=False, diffraction=False)
"""The map's ``raytracing`` defaults: Sionna's radio-map solver's own interactions (the
line of sight, specular reflection and refraction), 2e5 rays per cell to depth 2."""


@dataclasses.dataclass(frozen=True)
class RadioMapSettings:
    cell_size_m: float = 10.0
    height_m: float = 1.5
    margin_m: float = 200.0
    """The map covers the sites' bounding box grown by this much."""
    raytracing: TraceSettings = dataclasses.field(default_factory=lambda: MAP_RAYS)
    """The map's rays (:class:`~caviar_plugins.rt.settings.TraceSettings`; ``samples_per_src``
    is per cell, Sionna's ``samples_per_tx``; the shoot cache and the path buffer do not
    apply to a radio map)."""
    moved: ClassVar[dict[str, str]] = {"samples_per_tx": "raytracing.samples_per_src",
                                       "max_depth": "raytracing.max_depth"}

    def __post_init__(self):
        for key in ("cell_size_m", "height_m"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key}: expected a positive number, got {getattr(self, key)}")
        if self.margin_m < 0:
            raise ValueError(f"margin_m: expected >= 0, got {self.margin_m}")


def best_server_map(cells: Sequence[Cell], settings: RadioMapSettings, scene: str, num_prb: int,
                    noise_figure_db: float, base_dir: pathlib.Path | None = None, seed: int = 0) -> dict[str, Any]:
    """The map: grid centres ``x`` [nx] and ``y`` [ny], ``gain_db`` [cell, ny, nx] (path
    gain and pattern), ``rsrp_dbm`` [cell, ny, nx], ``best`` [ny, nx] (cell index, -1
    where no cell reaches) and ``sinr_db`` [ny, nx] on the best server (NaN where none)."""
    s = build_scene(scene, base_dir, frequency_hz=cells[0].carrier_hz, tx_array=AntennaArray(pattern="tr38901"),
                    rx_array=AntennaArray(), threads=settings.raytracing.threads,
                    transmitters=[Emitter(f"map-{c.index}", c.position,
                                          (float(np.radians(c.azimuth_deg)), float(np.radians(c.downtilt_deg)), 0.0))
                                  for c in cells])
    pos = np.array([c.position for c in cells])
    lo, hi = pos[:, :2].min(axis=0) - settings.margin_m, pos[:, :2].max(axis=0) + settings.margin_m
    rm = radio_map(s, settings.raytracing, seed, center=((lo + hi) / 2).tolist() + [settings.height_m],
                   size=(hi - lo).tolist(), cell_size=[settings.cell_size_m, settings.cell_size_m])
    gain = np.array(rm.path_gain)  # [cell, ny, nx]
    grid = np.array(rm.cell_centers)  # [ny, nx, 3]
    n_cell, ny, nx = gain.shape
    gain_db = 10 * np.log10(np.maximum(gain, 10 ** (NO_SIGNAL_DB / 10)))
    rx = rx_power_dbm(cells, gain_db.reshape(n_cell, -1).T)  # [points, cell]
    best = np.where(gain.reshape(n_cell, -1).max(axis=0) > 0, rx.argmax(axis=1), -1)
    sinr = sinr_db(cells, rx, best, noise_figure_db)
    return {"x": grid[0, :, 0], "y": grid[:, 0, 1], "gain_db": gain_db,
            "rsrp_dbm": rsrp_dbm(cells, rx, [num_prb] * n_cell).T.reshape(n_cell, ny, nx),
            "best": best.reshape(ny, nx), "sinr_db": sinr.reshape(ny, nx)}


def sinr_layer(result: dict[str, Any]) -> np.ndarray:
    """The SINR on the best server as an RGBA image, uint8 [ny, nx, 4]: one pixel per map
    cell, viridis over :data:`SINR_RANGE_DB`, transparent where no cell serves (NaN); row 0
    is the northmost ``y`` (an image's top), column 0 the westmost ``x``."""
    import matplotlib
    from matplotlib.colors import Normalize

    sinr = np.asarray(result["sinr_db"], dtype=float)
    rgba = matplotlib.colormaps["viridis"](Normalize(*SINR_RANGE_DB)(sinr), bytes=True)
    rgba[..., 3] = np.where(np.isfinite(sinr), 255, 0)
    x, y = result["x"], result["y"]
    if y[-1] > y[0]:
        rgba = rgba[::-1]
    if x[-1] < x[0]:
        rgba = rgba[:, ::-1]
    return np.ascontiguousarray(rgba)


def map_extent(result: dict[str, Any]) -> tuple[float, float, float, float]:
    """The area the map's cells cover, ``(x0, x1, y0, y1)``: their centres ± half a cell."""
    x, y = np.asarray(result["x"], dtype=float), np.asarray(result["y"], dtype=float)
    steps = [abs(a[-1] - a[0]) / (len(a) - 1) for a in (x, y) if len(a) > 1]
    if not steps:
        raise ValueError("radio map: a map of one cell has no cell size")
    dx = steps[0] if len(x) > 1 else steps[-1]
    dy = steps[-1] if len(y) > 1 else steps[0]
    return (float(x.min() - dx / 2), float(x.max() + dx / 2), float(y.min() - dy / 2), float(y.max() + dy / 2))


def layer_message(result: dict[str, Any], file: str = LAYER_FILE, *, height_m: float,
                  opacity: float = 0.6) -> dict[str, Any]:
    """The ``view.*`` payload that shows :func:`sinr_layer` in the browser view: ``file`` is
    the layer's path relative to the run directory (where :func:`save` wrote it), drawn at
    ``height_m`` (the map's, :attr:`RadioMapSettings.height_m`) over :func:`map_extent`."""
    return {"images": [{"file": file, "extent": [round(v, 3) for v in map_extent(result)], "z": float(height_m),
                        "opacity": float(opacity), "label": "best-server SINR (dB)"}]}


def save(result: dict[str, Any], cells: Sequence[Cell], out: pathlib.Path) -> list[pathlib.Path]:
    """``radio-map.npz`` (every array, and the cell names), ``radio-map.png`` (best server,
    and SINR on it) and ``radio-map-layer.png`` (:func:`sinr_layer`, for :func:`layer_message`)
    in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    npz = out / "radio-map.npz"
    np.savez_compressed(npz, cells=np.array([c.name for c in cells]), **result)
    extent = map_extent(result)  # the cells' edges: imshow puts pixel edges there
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    best = np.ma.masked_less(result["best"], 0)
    im = axes[0].imshow(best, origin="lower", extent=extent, cmap=plt.get_cmap("tab20", len(cells)),
                        vmin=-0.5, vmax=len(cells) - 0.5, interpolation="nearest")
    axes[0].set_title("best server")
    fig.colorbar(im, ax=axes[0], ticks=range(len(cells))).ax.set_yticklabels([c.name for c in cells])
    im = axes[1].imshow(result["sinr_db"], origin="lower", extent=extent, cmap="viridis", vmin=SINR_RANGE_DB[0],
                        vmax=SINR_RANGE_DB[1])
    axes[1].set_title("SINR on the best server (dB)")
    fig.colorbar(im, ax=axes[1])
    for ax in axes:
        for c in cells:
            ax.plot(*c.position[:2], "k^", ms=6)
        ax.set(xlabel="x (m)", ylabel="y (m)")
    fig.tight_layout()
    png = out / "radio-map.png"
    fig.savefig(png, dpi=90)
    plt.close(fig)
    layer = out / LAYER_FILE
    plt.imsave(layer, sinr_layer(result))
    return [npz, png, layer]
