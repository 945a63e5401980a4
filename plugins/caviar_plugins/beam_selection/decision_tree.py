"""The beam-selection decision tree: fitting, saving and loading, and its top-K accuracy."""

from __future__ import annotations

import pathlib
import pickle

import numpy as np

K_VALUES = (1, 2, 3, 4, 5, 10, 25, 50, 75, 100)
"""The K of the paper's top-K table."""
MAX_DEPTH = 15
"""The paper's tree depth."""


def train(positions: np.ndarray, best: np.ndarray, seed: int = 0, max_depth: int = MAX_DEPTH):
    """A tree predicting the best beam pair from (x, y, z)."""
    from sklearn.tree import DecisionTreeClassifier

    tree = DecisionTreeClassifier(max_depth=max_depth, random_state=seed)
    tree.fit(positions, best)
    return tree


def save(tree, path: pathlib.Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(tree))


def load_tree(path: pathlib.Path):
    return pickle.loads(pathlib.Path(path).read_bytes())


def top_k_accuracy(scores: np.ndarray, classes: np.ndarray, truth: np.ndarray, ks) -> dict[int, float]:
    """Share of samples whose true pair is among the k highest-scoring pairs."""
    order = classes[np.argsort(-scores, axis=1)]
    return {k: float(np.mean([t in row[:k] for t, row in zip(truth, order, strict=True)])) for k in ks}


def full_scores(tree, positions: np.ndarray, prior: np.ndarray, pairs: int = 256) -> np.ndarray:
    """Scores of all pairs: the tree's class probabilities; pairs it never predicts are
    ranked after them by how often they were best in training (``prior``)."""
    scores = np.zeros((len(positions), pairs))
    scores[:, tree.classes_] = tree.predict_proba(positions)
    return scores + 1e-9 * prior / max(prior.max(), 1)
