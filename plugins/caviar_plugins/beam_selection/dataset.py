"""The beam-selection dataset (Mob+3D/Comm-in-loop, no AI in the loop), like Raymobtime:
one npz record per step with the UAV position, the best beam pair, the LOS flag and
the gains of all pairs.

* :class:`BeamDataset` writes ``RUN_DIR/artifacts/NAME/step-NNNNNN-UE.npz``.
* :func:`load` reads a run's records back as arrays.

The UAV flies with :class:`~caviar_plugins.mobility.RandomWaypointFlight`.
"""

from __future__ import annotations

import pathlib

import numpy as np

import caviar
from caviar_plugins.schema import BEAM_GAINS, DATASET_RECORD, LINK, POSITIONS, every_ue, read_position, ue_of


class BeamDataset(caviar.Plugin):
    """Writes one npz record per UAV and step: position, best pair, LOS, gains."""

    subscribe = [POSITIONS, LINK, every_ue(BEAM_GAINS)]
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
        for m in inbox.on(every_ue(BEAM_GAINS)):
            ue = ue_of(m.topic)
            path = self.ctx.artifact_dir / f"step-{self.ctx.step:06d}-{ue}.npz"
            np.savez(path, position=self.positions[ue], best_pair=links[ue]["best_pair"],
                     los=links[ue]["los"], gains=m.data, time=t, n_paths=links[ue]["n_paths"])
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
