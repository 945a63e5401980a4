"""Beam selection from the UAV position: a scikit-learn decision tree (the paper's,
max depth 15), or the random and oracle baselines.

* ``tree``: predicts the beam pair (0 … 255) from (x, y, z) with a tree trained by
  ``python -m caviar_plugins.tools.training.train_tree`` (see
  :mod:`~caviar_plugins.beam_selection.decision_tree`).
* ``random``: a uniformly drawn pair (Rx 0–3 × Tx 0–63), seeded.
* ``oracle``: publishes nothing, so the communications module uses the best pair.
* ``tree`` also takes any pickled model with ``predict``; one with ``uses_previous``
  (:class:`~caviar_plugins.beam_selection.knn.GainKNN`) is given the previous step's
  gains from ``communications.beam_gains.<UE_Id>`` (publish_channels = true).
* ``previous``: the best pair of the previous step (from ``communications.link``): the
  selector that is given last step's beam sweep; the first step uses the best pair.

``protocol = "paper"`` changes ``random`` to the 2023 code's draws: one
``numpy.random.default_rng(1)`` per run, ``r = integers(0, 4)`` then
``t = integers(0, 64)`` every step, pair = 64·r + t.

Choices go to ``ai.beam.selection`` as ``{"UE_Id": …, "beam_pair": i}``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.beam_selection.decision_tree import load_tree
from caviar_plugins.schema import BEAM_GAINS, BEAM_SELECTION, LINK, POSITIONS, every_ue, read_position, ue_of

METHODS = ("tree", "random", "oracle", "previous")


class BeamSelector(caviar.Plugin):
    subscribe = [POSITIONS, LINK, every_ue(BEAM_GAINS)]
    publishes = (BEAM_SELECTION,)

    @dataclasses.dataclass
    class Params:
        method: str = "tree"
        model: str = ""
        """Pickled tree from ``train_tree`` (relative to the config file); needed for ``tree``."""
        pairs: int = 256
        protocol: str = "physical"
        """``physical`` or ``paper`` (changes only ``random``; see the module docstring)."""

        def __post_init__(self):
            paper.check_protocol(self.protocol)
            if self.method not in METHODS:
                raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
            if self.method == "tree" and not self.model:
                raise ValueError("method 'tree' needs `model`, a tree trained by "
                                 "`python -m caviar_plugins.tools.training.train_tree`")

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.tree: Any = None
        if p.method == "tree":
            self.tree = load_tree(ctx.resolve(p.model))
        self.paper_rng = np.random.default_rng(1)
        self.last_best: dict[str, int] = {}
        self.last_gains: dict[str, np.ndarray] = {}

    def state(self):
        # The model comes from setup; ctx.rng (method = "random") is saved by the host.
        return {"last_best": self.last_best, "last_gains": self.last_gains,
                "paper_rng": self.paper_rng.bit_generator.state}

    def restore(self, state):
        self.last_best, self.last_gains = state["last_best"], state["last_gains"]
        self.paper_rng.bit_generator.state = state["paper_rng"]

    def step(self, t, inbox):
        p = self.ctx.params
        for m in inbox.on(LINK):
            self.last_best[m.data["UE_Id"]] = int(m.data["best_pair"])
        for m in inbox.on(every_ue(BEAM_GAINS)):
            self.last_gains[ue_of(m.topic)] = np.asarray(m.data, dtype=float).reshape(1, -1)
        if p.method == "oracle":
            return
        for m in inbox.on(POSITIONS):
            if p.method == "previous":
                if m.data["UE_Id"] not in self.last_best:
                    continue
                pair = self.last_best[m.data["UE_Id"]]
            elif p.method == "random" and p.protocol == "paper":
                r = int(self.paper_rng.integers(0, 4))
                pair = r * 64 + int(self.paper_rng.integers(0, 64))
            elif p.method == "random":
                pair = int(self.ctx.rng.integers(p.pairs))
            elif getattr(self.tree, "uses_previous", False):  # e.g. GainKNN given last step's sweep
                prev = self.last_gains.get(m.data["UE_Id"])
                pair = int(self.tree.predict(read_position(m.data)[None, :], previous_gains=prev)[0])
            else:
                pair = int(self.tree.predict(read_position(m.data)[None, :])[0])
            yield BEAM_SELECTION, {"UE_Id": m.data["UE_Id"], "beam_pair": pair}
