"""A scikit-learn random forest evaluated with torch on its device, bit for bit as scikit-learn.

The main job's person detector is a pixel classifier: a forest of 40 trees of depth 14 over
each distinct pixel's features. Its tree walk was 70 % of a frame on the CPU, and on the lent
H200 the detector took 5.9 ms a frame there while the GPU idled (issue #53). :class:`TorchForest`
walks all trees at once on the device: the trees' nodes are tables (T trees × their most
nodes), a leaf points to itself, and each of ``max_depth`` rounds moves every (tree, row)
one level down with gathers. It is exact, not approximately equal:

* the test is scikit-learn's: the float32 feature widened to float64 against the float64
  threshold, ``x <= threshold`` goes left;
* a tree's probability is its leaf's value as scikit-learn returns it
  (``tree_.value``, normalised the way its ``predict_proba`` does where it holds counts);
* the trees' probabilities are summed in float64 one tree after the other in tree order, then
  divided by the number of trees: :meth:`PixelDetector.person_probability`'s order. The
  division is numpy's, on the host: CUDA's division of a tensor by a number multiplies by its
  inverse, which differs in the last bit (on the H200 the detections then differed).

``tests/test_yolo_torch.py`` compares it with ``predict_proba`` for equality on the CPU. Its
launches do not depend on the rows (about 6 per level and one per tree), so on CUDA a frame's
walk is one CUDA graph, captured once for each :meth:`TorchForest.bucket` of rows.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from caviar_plugins.torch_device import is_cuda, to_numpy, to_torch


def leaf_probabilities(tree) -> np.ndarray:
    """(nodes, classes) float64: what ``tree.predict_proba`` returns for a row ending in each node."""
    value = np.asarray(tree.tree_.value[:, 0, :tree.n_classes_], dtype=np.float64)
    sums = value.sum(axis=1)
    if np.allclose(sums[tree.tree_.children_left == -1], 1.0):
        return value  # (scikit-learn >= 1.4 keeps fractions)
    normalizer = sums[:, None].copy()  # (older ones kept counts and normalised in predict_proba)
    normalizer[normalizer == 0.0] = 1.0
    return value / normalizer


def unsupported(forest) -> str | None:
    """Why :class:`TorchForest` cannot walk ``forest`` bit for bit as scikit-learn does (None: it can)."""
    trees = getattr(forest, "estimators_", None)
    if trees is None or not len(trees) or not all(hasattr(t, "tree_") and hasattr(t, "predict_proba") for t in trees):
        return "not a scikit-learn forest of decision trees (RandomForestClassifier, ExtraTreesClassifier)"
    if getattr(forest, "n_outputs_", 1) != 1 or np.ndim(getattr(forest, "n_classes_", 0)) != 0:
        return "a forest of one output (classes of one target) is expected"
    if getattr(forest, "n_jobs", None) not in (None, 1):
        return f"n_jobs = {forest.n_jobs}: scikit-learn sums its trees in no fixed order then"
    return None


class TorchForest:
    """The ``forest`` (a fitted ``RandomForestClassifier``, one output) on torch ``device``:
    ``forest.column(x)`` is ``forest.predict_proba(x)[:, column]`` for feature rows ``x``
    (numpy (M, features)), as numpy float64."""

    def __init__(self, forest, device: Any, column: int = 1, cuda_graphs: bool | None = None):
        import torch

        why = unsupported(forest)
        if why is not None:
            raise ValueError(why)
        trees = forest.estimators_
        width = max(t.tree_.node_count for t in trees)
        n = len(trees)
        left = np.tile(np.arange(width, dtype=np.int64), (n, 1))  # (padding: leaves pointing to themselves)
        right, feature = left.copy(), np.zeros((n, width), dtype=np.int64)
        threshold = np.full((n, width), np.inf)
        prob = np.zeros((n, width))
        for k, tree in enumerate(trees):
            t = tree.tree_
            inner = t.children_left != -1
            m = t.node_count
            left[k, :m] = np.where(inner, t.children_left, np.arange(m))
            right[k, :m] = np.where(inner, t.children_right, np.arange(m))
            feature[k, :m] = np.where(inner, t.feature, 0)
            threshold[k, :m] = np.where(inner, t.threshold, np.inf)
            prob[k, :m] = leaf_probabilities(tree)[:, column]
        self.device = torch.device(device)
        self.trees, self.depth, self.features = n, max(t.tree_.max_depth for t in trees), forest.n_features_in_
        self.left, self.right, self.feature = (to_torch(a, self.device) for a in (left, right, feature))
        self.threshold, self.prob = to_torch(threshold, self.device), to_torch(prob, self.device)
        self.cuda_graphs = is_cuda(self.device) if cuda_graphs is None else bool(cuda_graphs)
        if self.cuda_graphs and not is_cuda(self.device):
            raise ValueError(f"cuda_graphs needs a CUDA device, not {self.device}")
        from caviar_plugins.vision.onnx_torch import CudaGraphs

        self._graphs = CudaGraphs(self._walk, "pixel forest") if self.cuda_graphs else None

    @staticmethod
    def bucket(rows: int) -> int:
        """The rows a CUDA graph is captured for: the next power of two, at least 1,024 (a
        frame's distinct rows vary; a few graphs serve them all, the padding's rows dropped)."""
        return max(1024, 1 << max(0, rows - 1).bit_length())

    def _walk(self, xt):
        """The probabilities of the columns of ``xt`` (features, M) float64 on the device."""
        import torch

        node = torch.zeros((self.trees, xt.shape[1]), dtype=torch.int64, device=self.device)
        for _ in range(self.depth):
            value = torch.gather(xt, 0, torch.gather(self.feature, 1, node))
            node = torch.where(value <= torch.gather(self.threshold, 1, node),
                               torch.gather(self.left, 1, node), torch.gather(self.right, 1, node))
        prob = torch.gather(self.prob, 1, node)
        total = torch.zeros(xt.shape[1], dtype=torch.float64, device=self.device)
        for k in range(self.trees):  # (in tree order, one add each: scikit-learn's sum)
            total += prob[k]
        return total  # (divided by the trees on the host: CUDA divides by a scalar as a product with its inverse)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        import torch

        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.features:
            raise ValueError(f"expected feature rows (M, {self.features}), got {x.shape}")
        if np.isnan(x).any():
            raise ValueError("feature rows with NaN: scikit-learn sends them by each node's missing_go_to_left; "
                             "walk these with scikit-learn")
        xt = np.ascontiguousarray(x.T, dtype=np.float64)  # (features, M): float32 widened, exactly
        if self._graphs is not None and self._graphs.on:
            from caviar_plugins.vision.onnx_torch import GPU_RUNS

            padded = np.zeros((self.features, self.bucket(x.shape[0])))
            padded[:, :x.shape[0]] = xt
            with GPU_RUNS:  # (a graph's buffers serve one run at a time: the detector's threads)
                out = self._graphs(to_torch(padded, self.device))
                if out is not None:
                    return to_numpy(out)[:x.shape[0]] / self.trees
        with torch.inference_mode():
            return to_numpy(self._walk(to_torch(xt, self.device))) / self.trees
