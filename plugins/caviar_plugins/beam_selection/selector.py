"""Beam selection from the UAV position: a scikit-learn decision tree (the paper's,
max depth 15), or the random and oracle baselines.

* ``tree``: predicts the beam pair (0 … 255) from (x, y, z) with a tree trained by
  ``python -m caviar_plugins.beam_selection.train_tree`` (see
  :mod:`~caviar_plugins.beam_selection.decision_tree`).
* ``random``: a uniformly drawn pair (Rx 0–3 × Tx 0–63), seeded.
* ``oracle``: publishes nothing, so the communications module uses the best pair.

Choices go to ``ai.beam.selection`` as ``{"UE_Id": …, "beam_pair": i}``.
"""

from __future__ import annotations

import dataclasses

import caviar
from caviar_plugins.beam_selection.decision_tree import load_tree
from caviar_plugins.schema import BEAM_SELECTION, POSITIONS, read_position

METHODS = ("tree", "random", "oracle")


class BeamSelector(caviar.Plugin):
    subscribe = [POSITIONS]
    publishes = (BEAM_SELECTION,)

    @dataclasses.dataclass
    class Params:
        method: str = "tree"
        model: str = ""
        """Pickled tree from ``train_tree`` (relative to the config file); needed for ``tree``."""
        pairs: int = 256

        def __post_init__(self):
            if self.method not in METHODS:
                raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
            if self.method == "tree" and not self.model:
                raise ValueError("method 'tree' needs `model`, a tree trained by "
                                 "`python -m caviar_plugins.beam_selection.train_tree`")

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.tree = None
        if p.method == "tree":
            self.tree = load_tree(ctx.resolve(p.model))

    def step(self, t, inbox):
        p = self.ctx.params
        if p.method == "oracle":
            return
        for m in inbox.on(POSITIONS):
            if p.method == "random":
                pair = int(self.ctx.rng.integers(p.pairs))
            else:
                pair = int(self.tree.predict(read_position(m.data)[None, :])[0])
            yield BEAM_SELECTION, {"UE_Id": m.data["UE_Id"], "beam_pair": pair}
