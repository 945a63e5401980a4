"""The beam-selection dataset (Mob+3D/Comm-in-loop, no AI in the loop), like Raymobtime:
one npz record per step with the UAV position, the best beam pair, the LOS flag and
the gains of all pairs and, where a ``lidar`` or ``camera`` module runs, the UE's LiDAR
sweep and camera image of that step (multimodal, as Raymobtime pairs them).

* :class:`BeamDataset` writes ``RUN_DIR/artifacts/NAME/step-NNNNNN-UE.npz``.
* :func:`load` reads a run's records back as arrays (:func:`load_multimodal`: with the
  LiDAR sweeps and images);
* ``caviar-core export raymobtime`` writes them in Raymobtime's files
  (:mod:`caviar_plugins.tools.export.raymobtime`).

The UAV flies with :class:`~caviar_plugins.mobility.RandomWaypointFlight`.
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

import caviar
from caviar_plugins.schema import (
    BEAM_GAINS,
    CAMERA,
    DATASET_RECORD,
    LIDAR,
    LINK,
    POSITIONS,
    every_ue,
    read_position,
    ue_of,
)


class BeamDataset(caviar.Plugin):
    """Writes one npz record per UAV and step: position, best pair, LOS, gains, and the
    step's LiDAR sweep (the last, ``lidar``: n × 6) and camera image (``image``) when those
    modules run."""

    subscribe = [POSITIONS, LINK, every_ue(BEAM_GAINS), every_ue(LIDAR), every_ue(CAMERA)]
    optional = (every_ue(LIDAR), every_ue(CAMERA))  # (the other modalities, when they run)
    publishes = (DATASET_RECORD,)

    def setup(self, ctx):
        self.ctx = ctx
        self.positions: dict[str, np.ndarray] = {}

    def state(self):
        return {"positions": self.positions}

    def restore(self, state):
        self.positions = state["positions"]

    def step(self, t, inbox):
        for m in inbox.on(POSITIONS):
            self.positions[m.data["UE_Id"]] = read_position(m.data)
        links = {m.data["UE_Id"]: m.data for m in inbox.on(LINK)}
        sweeps = {ue_of(m.topic): np.asarray(m.data) for m in inbox.on(every_ue(LIDAR))}  # (the last one)
        images = {ue_of(m.topic): np.asarray(m.data) for m in inbox.on(every_ue(CAMERA))}
        for m in inbox.on(every_ue(BEAM_GAINS)):
            ue = ue_of(m.topic)
            path = self.ctx.artifact_dir / f"step-{self.ctx.step:06d}-{ue}.npz"
            record: dict[str, Any] = {
                "position": self.positions[ue], "best_pair": links[ue]["best_pair"], "los": links[ue]["los"],
                "gains": m.data, "time": t, "n_paths": links[ue]["n_paths"]}
            record.update({k: v for k, v in (("lidar", sweeps.get(ue)), ("image", images.get(ue))) if v is not None})
            np.savez(path, **record)
            yield DATASET_RECORD, caviar.Artifact(path)


def load(run_dir: str | pathlib.Path) -> dict[str, np.ndarray]:
    """All records of a run: position (N, 3), best_pair (N,), los (N,), gains (N, 4, 64),
    time (N,) and, where recorded, n_paths (N,)."""
    files = sorted(pathlib.Path(run_dir).glob("artifacts/*/step-*.npz"))
    if not files:
        raise FileNotFoundError(f"{run_dir}: no dataset records (artifacts/*/step-*.npz)")
    records = [np.load(f) for f in files]
    keys = ["position", "best_pair", "los", "gains", "time"]
    if all("n_paths" in r for r in records):
        keys.append("n_paths")
    return {k: np.stack([r[k] for r in records]) for k in keys}


def load_multimodal(run_dir: str | pathlib.Path) -> tuple[dict[str, np.ndarray], list[np.ndarray | None],
                                                          list[np.ndarray | None], list[str]]:
    """:func:`load`'s arrays, each record's LiDAR sweep (n × 6) and camera image (None
    where the record has none), and each record's UE id, in the same order."""
    files = sorted(pathlib.Path(run_dir).glob("artifacts/*/step-*.npz"))
    arrays = load(run_dir)
    sweeps, images = [], []
    for f in files:
        with np.load(f) as r:
            sweeps.append(r["lidar"] if "lidar" in r else None)
            images.append(r["image"] if "image" in r else None)
    ues = [f.stem.split("-", 2)[2] for f in files]
    return arrays, sweeps, images, ues
