"""``caviar-core export raymobtime``: a beam-dataset run in the files of Raymobtime, the
multimodal datasets (ray-traced channels, LiDAR, cameras) of the paper's group
(Klautau et al., ITA 2018; the ITU AI/ML in 5G challenge's beam-selection task).

    caviar-core export raymobtime RUN_DIR OUT [--grid 40,40,20] [--cell 1.0]

From the records ``beam-dataset`` wrote (:func:`~caviar_plugins.beam_selection.dataset.load_multimodal`),
OUT gets:

- ``CoordVehiclesRxPerScene.csv``: one row per record, Raymobtime's columns ``EpisodeID``
  (0: one run), ``SceneID`` (the step), ``VehicleArrayID`` (the UE's index), ``VehicleName``
  (its UE id), ``Val`` (``V``: every record has a channel), ``x``, ``y``, ``z`` (scene
  frame, m), ``LOS`` (``LOS=1`` / ``LOS=0``);
- ``beams_output.npz``: ``output_classification`` (N × Rx beams × Tx beams, float32): the
  beam-pair gains, as Raymobtime's ``beams_output`` files hold them;
- ``lidar_input.npz``: ``input_classification`` (N × X × Y × Z, int8), as Raymobtime's
  ``lidar_input`` files: 1 where a LiDAR return fell in a cell, 0 elsewhere, −2 the UE's
  own cell and −1 the cell toward the base station (see below); with the records that
  have a sweep;
- ``img_input.npz``: ``inputs`` (N × H × W × 3, uint8), the camera images, with the
  records that have one;
- ``meta.json``: the run, the grid, the transmitter, which records have which modality,
  and what differs from Raymobtime.

Where it differs from Raymobtime: its LiDAR grid (20 × 200 × 10 cells of the whole street
around the base station, from the *receiver*'s point cloud merged over the scene) is fixed to
the street; here the grid is centred on the UE (a UAV moves over the whole area), so the base
station, usually outside it, is marked at the grid's boundary cell on the straight line toward
it. The beam codebooks are the project's (DFT beams of the link's arrays), not Raymobtime's.
"""

from __future__ import annotations

import csv
import json
import pathlib
from typing import Any

import numpy as np

OBSTACLE, BASE_STATION, UE = 1, -1, -2


class ExportError(ValueError):
    """Bad input: named in one line."""


def occupancy_grid(points: np.ndarray, centre: np.ndarray, shape: tuple[int, int, int], cell_m: float,
                   base_station: np.ndarray | None = None, below_m: float | None = None) -> np.ndarray:
    """The int8 grid (X, Y, Z) of ``cell_m`` cells around ``centre`` (horizontally centred;
    vertically from ``below_m`` under it, by default 4/5 of the grid below): 1 in every cell
    holding a point of ``points`` (n × ≥3), −2 in the UE's own cell, −1 in the cell where
    the line toward ``base_station`` leaves the grid (or its cell, when inside)."""
    dims = np.array([int(v) for v in shape])
    grid = np.zeros(tuple(dims), dtype=np.int8)
    size = dims.astype(float) * cell_m
    below = 0.8 * size[2] if below_m is None else below_m
    origin = np.asarray(centre, dtype=float) - [size[0] / 2, size[1] / 2, below]

    def cell_of(xyz: np.ndarray) -> np.ndarray:
        return np.floor((xyz - origin) / cell_m).astype(np.int64)

    if len(points):
        idx = cell_of(np.asarray(points, dtype=float)[:, :3])
        inside = np.all((idx >= 0) & (idx < dims), axis=1)
        grid[tuple(idx[inside].T)] = OBSTACLE
    if base_station is not None:
        d = np.asarray(base_station, dtype=float) - centre
        # The largest step along d that stays inside the grid's box (a hair inside its faces).
        lo, hi = origin - centre + 1e-6, origin + size - centre - 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            limits = np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf))
        s = min(1.0, float(np.min(limits)))
        grid[tuple(np.clip(cell_of(centre + s * d), 0, dims - 1))] = BASE_STATION
    grid[tuple(np.clip(cell_of(np.asarray(centre, dtype=float)), 0, dims - 1))] = UE
    return grid


def transmitter_of(config_text: str) -> list[float] | None:
    """The ray-traced link's transmitter position from a run's configuration: its module's
    ``tx_position`` or that plugin's default; None when no such module."""
    import tomllib

    from caviar_plugins.radio.free_space_link import FreeSpaceLink

    cfg = tomllib.loads(config_text)
    for module in cfg.get("modules", {}).values():
        if module.get("plugin") in ("sionna-link", "free-space-link", "sionna-traffic-link"):
            given = module.get("params", {}).get("tx_position")
            return [float(v) for v in (given or FreeSpaceLink.Params().tx_position)]
    return None


def export_raymobtime(run_dir: pathlib.Path, out: pathlib.Path, grid: tuple[int, int, int] = (40, 40, 20),
                      cell_m: float = 1.0, tx: list[float] | None = None) -> dict[str, Any]:
    """Writes OUT (see the module docstring); returns what ``meta.json`` holds."""
    from caviar.rundir import RunDir
    from caviar_plugins.beam_selection.dataset import load_multimodal

    run_dir = pathlib.Path(run_dir)
    try:
        RunDir(run_dir).require("; give the folder of a run of `caviar-core run`")
    except FileNotFoundError as e:
        raise ExportError(str(e)) from None
    if out.exists():
        raise ExportError(f"{out}: exists; give a new folder")
    if len(grid) != 3 or min(grid) < 1 or not cell_m > 0:
        raise ExportError(f"--grid/--cell: expected three cell counts >= 1 and a cell > 0 m, got {grid} and {cell_m}")
    try:
        arrays, sweeps, images, ues = load_multimodal(run_dir)
    except FileNotFoundError as e:
        raise ExportError(f"{e} (a run with a beam-dataset module)") from None
    if tx is None:
        tx = transmitter_of(RunDir(run_dir).config_text())
    if tx is None:
        raise ExportError("--tx: the run has no link module to take the transmitter from; give --tx X,Y,Z")
    out.mkdir(parents=True)
    names = sorted(set(ues))
    steps = [int(f.stem.split("-")[1]) for f in sorted(run_dir.glob("artifacts/*/step-*.npz"))]
    with open(out / "CoordVehiclesRxPerScene.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["EpisodeID", "SceneID", "VehicleArrayID", "VehicleName", "Val", "x", "y", "z", "LOS"])
        for k, (ue, step) in enumerate(zip(ues, steps, strict=True)):
            x, y, z = (float(v) for v in arrays["position"][k])
            w.writerow([0, step, names.index(ue), ue, "V", f"{x:.3f}", f"{y:.3f}", f"{z:.3f}",
                        f"LOS={int(bool(arrays['los'][k]))}"])
    np.savez_compressed(out / "beams_output.npz", output_classification=arrays["gains"].astype(np.float32))
    lidar = [(k, s) for k, s in enumerate(sweeps) if s is not None]
    with_lidar = [k for k, _ in lidar]
    if lidar:
        grids = np.stack([occupancy_grid(s, arrays["position"][k], grid, cell_m, np.asarray(tx)) for k, s in lidar])
        np.savez_compressed(out / "lidar_input.npz", input_classification=grids, records=np.array(with_lidar))
    shot = [(k, im) for k, im in enumerate(images) if im is not None]
    with_image = [k for k, _ in shot]
    if shot:
        np.savez_compressed(out / "img_input.npz", inputs=np.stack([im for _, im in shot]),
                            records=np.array(with_image))
    meta = {"run": str(run_dir), "records": len(ues), "ues": names, "transmitter": tx,
            "gains_shape": list(arrays["gains"].shape[1:]),
            "lidar": {"records": len(with_lidar), "grid": list(grid), "cell_m": cell_m,
                      "values": {"obstacle": OBSTACLE, "base_station": BASE_STATION, "ue": UE},
                      "frame": "centred on the UE horizontally; from 0.8 of its height below it"},
            "images": len(with_image),
            "differs_from_raymobtime": [
                "the LiDAR grid is centred on the UE, not fixed to the street; the base station is marked where "
                "the line toward it leaves the grid",
                "the beam codebooks are the link's DFT beams, not Raymobtime's",
                "one episode per run (EpisodeID 0), one scene per step (SceneID)"]}
    (out / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta
