"""Issue #18 (faster steps): each fast path gives what the path it replaces gives."""

import numpy as np
import pytest

from caviar_plugins.vision import VisualConfig, VisualScene, packet_loss
from caviar_plugins.vision import person_detector as detector


@pytest.fixture(scope="module")
def visual():
    return VisualScene(VisualConfig(), seed=1)


def views(visual, n: int, seed: int = 0) -> list[np.ndarray]:
    """Positions over the targets and along the route, at altitudes with both look-at
    roundings (two distinct rotation matrices occur among them)."""
    rng = np.random.default_rng(seed)
    targets = np.array(visual.cfg.targets)
    return [np.r_[targets[i % len(targets)] + rng.normal(0, 3, 2), rng.uniform(6.0, 14.0)] for i in range(n)]


def test_batched_camera_renders_the_per_uav_images_bit_for_bit(visual):
    pos = views(visual, 21)
    batched = visual.render_many(pos, chunk=8)  # several chunks, one partial
    for p, (image, labels) in zip(pos, batched, strict=True):
        ref_image, ref_labels = visual.render_labelled(p)
        np.testing.assert_array_equal(image, ref_image)
        np.testing.assert_array_equal(labels, ref_labels)
    assert any((lab >= 0).any() for _, lab in batched), "no person in view: the test shows nothing"
    assert len(visual._ray_cache) >= 1


@pytest.fixture(scope="module")
def model():
    return detector.train(count=30, seed=7)


def test_vectorised_detector_finds_what_the_per_image_detector_finds(visual, model):
    rng = np.random.default_rng(5)
    images = [im for im, _ in visual.render_many(views(visual, 12, seed=1))]
    images = [packet_loss(im, rate, rng) for im, rate in zip(images, [0.0, 0.01, 0.25, 0.5] * 3, strict=True)]
    batch = model.detect_many(images)
    single = [model.detect(im) for im in images]
    assert batch == single
    assert sum(len(d) for d in single) > 0, "nothing detected: the test shows nothing"


def test_unique_rows_is_exact_even_with_hash_collisions(monkeypatch):
    rng = np.random.default_rng(0)
    words = rng.integers(0, 4, size=(5000, 3)).astype(np.uint64)
    first, inverse = detector.unique_rows(words)
    np.testing.assert_array_equal(words[first][inverse], words)
    assert len(first) == len(np.unique(words, axis=0))
    # A hash that collides everything: still exact.
    real_unique = np.unique

    def colliding(h, **kw):
        return real_unique(np.zeros_like(h), **kw)

    monkeypatch.setattr(detector.np, "unique", colliding)
    first, inverse = detector.unique_rows(words)
    np.testing.assert_array_equal(words[first][inverse], words)
