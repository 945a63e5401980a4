"""Beam selection from the UAV position: a scikit-learn decision tree (the paper's,
max depth 15), or the random and oracle baselines.

* ``tree``: predicts the beam pair (0 … 255) from (x, y, z) with a tree trained by
  ``python -m caviar_plugins.beam_selection train`` (see :func:`train`).
* ``random``: a uniformly drawn pair (Rx 0–3 × Tx 0–63), seeded.
* ``oracle``: publishes nothing, so the communications module uses the best pair.

Choices go to ``ai.beam.selection`` as ``{"UE_Id": …, "beam_pair": i}``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import pickle

import numpy as np

import caviar

SELECTION = "ai.beam.selection"
METHODS = ("tree", "random", "oracle")


class BeamSelector(caviar.Plugin):
    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params:
        method: str = "tree"
        model: str = ""
        """Pickled tree from ``train`` (relative to the config file); needed for ``tree``."""
        pairs: int = 256

        def __post_init__(self):
            if self.method not in METHODS:
                raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
            if self.method == "tree" and not self.model:
                raise ValueError("method 'tree' needs `model`, a tree trained by "
                                 "`python -m caviar_plugins.beam_selection train`")

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.tree = None
        if p.method == "tree":
            self.tree = pickle.loads(ctx.resolve(p.model).read_bytes())

    def step(self, t, inbox):
        p = self.ctx.params
        if p.method == "oracle":
            return
        for m in inbox.on("3D.mobility.positions"):
            pos = m.data["position"]
            if p.method == "random":
                pair = int(self.ctx.rng.integers(p.pairs))
            else:
                pair = int(self.tree.predict(np.array([[pos["x"], pos["y"], pos["z"]]]))[0])
            yield SELECTION, {"UE_Id": m.data["UE_Id"], "beam_pair": pair}


def top_k_accuracy(scores: np.ndarray, classes: np.ndarray, truth: np.ndarray, ks) -> dict[int, float]:
    """Share of samples whose true pair is among the k highest-scoring pairs."""
    order = classes[np.argsort(-scores, axis=1)]
    return {k: float(np.mean([t in row[:k] for t, row in zip(truth, order)])) for k in ks}


def train(positions: np.ndarray, best: np.ndarray, seed: int = 0, max_depth: int = 15):
    from sklearn.tree import DecisionTreeClassifier

    tree = DecisionTreeClassifier(max_depth=max_depth, random_state=seed)
    tree.fit(positions, best)
    return tree


def save(tree, path: pathlib.Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(tree))
