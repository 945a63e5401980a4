"""A beam selector better than the paper's tree on the same data: k nearest neighbours
on the UAV position that picks the pair of largest mean gain among the neighbours.

The tree learns only the label (the best pair) of each training sample. The dataset
holds the gains of all 256 pairs, and with the 2023 protocol's 5.714 λ grating lobes
the best pair flips between nearby positions while a good pair stays good: averaging
the neighbours' (normalised) gains and taking the argmax picks the pair that is
reliably strong around the position. Pickled, it is used in the loop like the tree
(``beam-selector`` with ``method = "tree"``, ``model = …``): it has ``predict``.
"""

from __future__ import annotations

import numpy as np


class GainKNN:
    def __init__(self, k: int = 5, weights: str = "distance"):
        self.k = k
        self.weights = weights

    def fit(self, positions: np.ndarray, gains: np.ndarray) -> GainKNN:
        """positions (N, 3); gains (N, C_rx, C_tx) or (N, pairs)."""
        from sklearn.neighbors import NearestNeighbors

        g = np.asarray(gains, dtype=float).reshape(len(gains), -1)
        self.gains_ = g / np.maximum(g.max(axis=1, keepdims=True), 1e-30)  # each sample's best = 1
        self.nn_ = NearestNeighbors(n_neighbors=min(self.k, len(g))).fit(np.asarray(positions, dtype=float))
        return self

    def scores(self, positions: np.ndarray) -> np.ndarray:
        """Mean normalised gain of every pair over the k nearest training positions."""
        dist, idx = self.nn_.kneighbors(np.atleast_2d(np.asarray(positions, dtype=float)))
        w = 1 / np.maximum(dist, 1e-3) if self.weights == "distance" else np.ones_like(dist)
        return np.einsum("nk,nkp->np", w, self.gains_[idx]) / w.sum(axis=1, keepdims=True)

    def predict(self, positions: np.ndarray) -> np.ndarray:
        return np.argmax(self.scores(positions), axis=1)
