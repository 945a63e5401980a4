"""LiDAR-aided beam selection (issue #43, part 3): its targets, scores and training against
hand computations and a task only the LiDAR can solve."""

from __future__ import annotations

import numpy as np
import pytest

from caviar_plugins.tools.baselines import lidar_selector as ls


def test_soft_targets_keep_the_pairs_within_6_db_normalised():
    gains = np.array([[1.0, 0.5, 0.2, 0.1]])  # 0, -3, -7, -10 dB
    np.testing.assert_allclose(ls.soft_targets(gains), [[1 / 1.5, 0.5 / 1.5, 0.0, 0.0]])


def test_top_k_and_the_throughput_ratio_by_hand():
    gains = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])
    scores = np.array([[0.0, 1.0, 0.5], [1.0, 0.0, 0.5]])  # second-best first, then best
    k = ls.top_k(scores, gains, ks=(1, 2, 3))
    assert k == {"top1": 0.5, "top2": 1.0, "top3": 1.0}
    assert ls.throughput_ratio(gains, gains) == pytest.approx(1.0)  # the oracle's own choice
    assert ls.throughput_ratio(scores, gains, sweep=2) == pytest.approx(1.0)  # sweeping 2 finds the best
    assert ls.throughput_ratio(scores, gains) < 1.0


def test_the_cnn_learns_what_only_the_lidar_shows():
    """Which of 8 pairs is best depends on which quadrant of the grid holds an obstacle, at
    random positions: the CNN finds it, position-only k-NN cannot."""
    from caviar_plugins.beam_selection.knn import GainKNN
    from caviar_plugins.torch_device import resolve

    rng = np.random.default_rng(0)
    n, pairs = 320, 8
    grids = np.zeros((n, 21, 40, 40), dtype=np.float32)
    quadrant = rng.integers(0, 4, n)
    for i, q in enumerate(quadrant):
        x0, y0 = (q % 2) * 20 + 5, (q // 2) * 20 + 5
        grids[i, 3:8, x0:x0 + 10, y0:y0 + 10] = 1.0  # a building in that quadrant
    positions = rng.uniform(-50, 50, (n, 3))
    gains = np.full((n, pairs), 1e-3) * rng.uniform(0.5, 1.0, (n, pairs))
    gains[np.arange(n), 2 * quadrant] = 1.0
    train, test = slice(0, 240), slice(240, n)
    model, mean, std = ls.train_cnn(grids[train], positions[train], ls.soft_targets(gains[train]), False,
                                    epochs=15, seed=0, device=resolve("cpu"))
    cnn = ls.top_k(ls.predict(model, grids[test], positions[test], mean, std, resolve("cpu")), gains[test])
    knn = ls.top_k(GainKNN(k=5).fit(positions[train], gains[train]).scores(positions[test]), gains[test])
    assert cnn["top1"] >= 0.95, cnn
    assert knn["top1"] <= 0.5, knn


def test_a_record_with_no_path_gives_no_target_and_no_nan():
    targets = ls.soft_targets(np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.9]]))
    assert np.all(np.isfinite(targets)) and targets[0].sum() == 0.0 and targets[1].sum() == pytest.approx(1.0)
