"""The person detector's models: the project's pixel classifier, trained on its own renders, and
the wrapper that gives a box detector (YOLO) the same interface.

No pretrained weights can be downloaded, so the pixel classifier is learned from frames the
camera module renders, with exact labels from the renderer (each pixel's shape): a random
forest classifies pixels from their colour and neighbourhood, and connected regions of person
pixels of plausible size are the detections. Training includes packet-loss-degraded frames,
so the detector meets the images it gets in the loop. The plugin is
:mod:`caviar_plugins.vision.person_detector`.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import pickle
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from caviar_plugins.assets import DATA
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.vision.camera import VisualConfig, VisualScene
from caviar_plugins.vision.image_link import packet_loss

TRAINING_SEED = 1234
MODEL_VERSION = 2


def features(image: np.ndarray) -> np.ndarray:
    """Per-pixel features (H·W, 10): colour, 5×5 mean colour, chroma, 9×9 mean chroma."""
    from scipy.ndimage import uniform_filter

    x = image.astype(np.float32) / 255.0
    local = uniform_filter(x, size=(5, 5, 1))
    chroma = (x.max(axis=2) - x.min(axis=2))[..., None]
    wide = uniform_filter(chroma, size=(9, 9, 1))
    return np.concatenate([x, local, chroma, wide, x[..., :1] - x[..., 1:2], x[..., 2:3] - x[..., 1:2]],
                          axis=2).reshape(-1, 10)


def unique_rows(words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``first`` of the distinct rows of a (M, K) uint64 array and ``inverse``
    such that ``words[first][inverse]`` equals ``words``.

    Rows are hashed (a multiply-add over their words) and sorted once; a hash collision
    is caught by comparing each row with its representative, and the colliding rows
    get representatives of their own: the result is exact whatever the hash does."""
    n = len(words)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    coef = np.random.default_rng(0x5EED).integers(1, 2**63, size=words.shape[1], dtype=np.uint64) | np.uint64(1)
    h = np.zeros(n, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for j in range(words.shape[1]):
            h = h * np.uint64(0x100000001B3) + words[:, j] * coef[j]
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    rep = first[inverse]
    differs = words[rep, 0] != words[:, 0]
    for j in range(1, words.shape[1]):
        differs |= words[rep, j] != words[:, j]
    bad = np.flatnonzero(differs)
    if len(bad):  # hash collisions: those rows stand for themselves
        inverse = inverse.copy()
        inverse[bad] = len(first) + np.arange(len(bad))
        first = np.concatenate([first, bad])
    return first, inverse


def feature_parts(images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The parts of :func:`features` for a stack of images (N, H, W, 3), image by image
    the same values (the filters have size 1 along the stack): colour, 5×5 mean
    colour, chroma, 9×9 mean chroma, each flattened to (N·H·W, C)."""
    from scipy.ndimage import uniform_filter

    x = images.astype(np.float32) / 255.0
    local = uniform_filter(x, size=(1, 5, 5, 1))
    # max/min over 3 channels written out (numpy's reduce over a short last axis is slow).
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    chroma = (np.maximum(np.maximum(r, g), b) - np.minimum(np.minimum(r, g), b))[..., None]
    wide = uniform_filter(chroma, size=(1, 9, 9, 1))
    return x.reshape(-1, 3), local.reshape(-1, 3), chroma.reshape(-1, 1), wide.reshape(-1, 1)


def assemble_features(x: np.ndarray, local: np.ndarray, chroma: np.ndarray, wide: np.ndarray) -> np.ndarray:
    """The (M, 10) rows of :func:`features` from its parts (rows of :func:`feature_parts`)."""
    return np.concatenate([x, local, chroma, wide, x[:, :1] - x[:, 1:2], x[:, 2:3] - x[:, 1:2]], axis=1)


@dataclasses.dataclass
class Detection:
    row: float
    col: float
    pixels: int
    """Pixels of the region (pixel classifier) or of the box (YOLO)."""
    score: float
    box: tuple[float, float, float, float] | None = None
    """x0, y0, x1, y1 in image pixels (YOLO; the pixel classifier when asked), or None."""


class PixelDetector:
    def __init__(self, forest, min_pixels: int = 12, threshold: float = 0.5):
        self.forest = forest
        self.min_pixels = min_pixels
        self.threshold = threshold
        self.on_device: Any = None
        """The forest on torch's device (:class:`~caviar_plugins.vision.forest_torch.TorchForest`,
        :meth:`to_device`), or None: scikit-learn's tree walk on the CPU. The same numbers."""

    def to_device(self, device) -> PixelDetector:
        """This detector with its forest walked by torch on ``device`` (the GPU of ``runtime =
        "torch"``), bit for bit as scikit-learn walks it."""
        from caviar_plugins.vision.forest_torch import TorchForest, unsupported

        why = unsupported(self.forest)
        if why is not None:
            raise ValueError(f"runtime = 'torch': the pixel model is {why}")
        self.on_device = TorchForest(self.forest, device)
        return self

    def person_probability(self, x: np.ndarray) -> np.ndarray:
        """Each feature row's probability of being a person's pixel: the forest's
        ``predict_proba(x)[:, 1]``, bit for bit. A scikit-learn forest trained with
        ``n_jobs = 1`` (as :func:`train` does) is evaluated here the way its
        ``predict_proba`` does it (each tree's probabilities summed in tree order into
        float64, divided by the number of trees) without joblib's dispatch of one task per
        tree, which cost 7 ms of the 12 ms of a 160 × 120 image. Any other model (an
        ONNX one, a forest with other ``n_jobs``) is asked for ``predict_proba``."""
        if self.on_device is not None and not np.isnan(x).any():  # (NaN: scikit-learn's missing-value rules)
            return self.on_device(x)
        trees = getattr(self.forest, "estimators_", None)
        if trees is None or getattr(self.forest, "n_jobs", None) not in (None, 1) or \
                np.ndim(self.forest.n_classes_) != 0 or x.ndim != 2 or x.shape[1] != self.forest.n_features_in_:
            return self.forest.predict_proba(x)[:, 1]
        x = np.ascontiguousarray(x, dtype=np.float32)
        total = np.zeros((len(x), self.forest.n_classes_), dtype=np.float64)
        for tree in trees:
            total += tree.predict_proba(x, check_input=False)
        total /= len(trees)
        return total[:, 1]

    def mask(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from scipy.ndimage import binary_dilation

        prob = self.person_probability(features(image)).reshape(image.shape[:2])
        # Lost packets arrive as zero bytes: pixels that are exactly black, and their
        # neighbours (whose features saw the hole), are not evidence of anything.
        missing = binary_dilation(np.all(image == 0, axis=2), iterations=2)
        return (prob >= self.threshold) & ~missing, prob

    def detect(self, image: np.ndarray, boxes: bool = False) -> list[Detection]:
        """The person regions of ``image``; with ``boxes``, each with its bounding box (x0, y0,
        x1, y1, pixel edges), as a box detector gives them."""
        mask, prob = self.mask(image)
        return self._regions(mask, prob, boxes)

    def _regions(self, mask: np.ndarray, prob: np.ndarray, boxes: bool = False) -> list[Detection]:
        from scipy.ndimage import find_objects, label

        regions, n = label(mask)
        out = []
        # Each region searched inside its bounding box: the same pixels in the same
        # (row-major) order as over the whole image, so the same sums.
        for k, box in enumerate(find_objects(regions), start=1):
            if box is None:
                continue
            rows, cols = np.nonzero(regions[box] == k)
            if len(rows) >= self.min_pixels:
                rows, cols = rows + box[0].start, cols + box[1].start
                edges = (float(box[1].start), float(box[0].start), float(box[1].stop), float(box[0].stop))
                out.append(Detection(float(rows.mean()), float(cols.mean()), int(len(rows)),
                                     float(prob[rows, cols].mean()), edges if boxes else None))
        return out

    def detect_many(self, images: list[np.ndarray], pool: ThreadPoolExecutor | None = None,
                    chunks: int = 0) -> list[list[Detection]]:
        """:meth:`detect` for a step's images in one batch, the same detections: the
        features of all images at once, one classification of their distinct feature
        rows (:func:`unique_rows`), then connected regions per image.

        With a thread ``pool``, the images are split into ``chunks`` contiguous batches
        (default 2; two per thread works best) detected side by side: the sort, the
        filters and the forest's tree walk release the GIL. A pixel's probability does not depend on the
        other rows of its batch, so the detections are the same for any split."""
        if pool is not None and len(images) > 1:
            k = min(len(images), chunks or 2)
            bounds = [round(i * len(images) / k) for i in range(k + 1)]
            parts = pool.map(self._detect_batch, [images[a:b] for a, b in zip(bounds, bounds[1:], strict=False)])
            return [found for part in parts for found in part]
        return self._detect_batch(images)

    def _detect_batch(self, images: list[np.ndarray]) -> list[list[Detection]]:
        from scipy.ndimage import binary_dilation, generate_binary_structure

        if not images:
            return []
        shapes = {im.shape for im in images}
        if len(shapes) > 1:
            return [self.detect(im) for im in images]
        stack = np.stack(images)
        n, h, w = stack.shape[:3]
        x, local, chroma, wide = feature_parts(stack)
        # A feature row is a function of the pixel's colour (3 bytes), its 5×5 mean
        # colour and 9×9 mean chroma (float32 bits): 3 words identify it exactly.
        rgb = stack.reshape(-1, 3).astype(np.uint64)
        lb = local.view(np.uint32).astype(np.uint64)
        words = np.stack([rgb[:, 0] | rgb[:, 1] << np.uint64(8) | rgb[:, 2] << np.uint64(16)
                          | wide.view(np.uint32)[:, 0].astype(np.uint64) << np.uint64(32),
                          lb[:, 0] | lb[:, 1] << np.uint64(32), lb[:, 2]], axis=1)
        first, inverse = unique_rows(words)
        f = assemble_features(x[first], local[first], chroma[first], wide[first])
        prob = self.person_probability(f)[inverse].reshape(n, h, w)
        # The 2-D cross of binary_dilation's default, on each image alone.
        cross = generate_binary_structure(2, 1)[None]
        cross = np.concatenate([np.zeros_like(cross), cross, np.zeros_like(cross)])
        black = (stack[..., 0] == 0) & (stack[..., 1] == 0) & (stack[..., 2] == 0)
        missing = binary_dilation(black, structure=cross, iterations=2)
        mask = (prob >= self.threshold) & ~missing
        return [self._regions(mask[i], prob[i]) for i in range(n)]

    def save(self, path: pathlib.Path) -> None:
        # The forest and plain settings only: the file does not depend on where this
        # class lives (e.g. __main__ when trained with `python -m`).
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps({"format": "caviar-person-detector", "version": MODEL_VERSION,
                                      "forest": self.forest, "min_pixels": self.min_pixels,
                                      "threshold": self.threshold}))
        tmp.replace(path)

    @staticmethod
    def load(path: pathlib.Path) -> "PixelDetector":
        if pathlib.Path(path).suffix == ".onnx":
            return PixelDetector(OnnxPixelModel(path))
        if not pathlib.Path(path).is_file():
            raise ValueError(f"{path}: no such detector model file")
        try:
            data = pickle.loads(pathlib.Path(path).read_bytes())
        except (OSError, pickle.UnpicklingError, AttributeError, EOFError) as e:
            raise ValueError(f"{path}: cannot read the detector model: {e}") from None
        if not isinstance(data, dict) or data.get("format") != "caviar-person-detector":
            raise ValueError(f"{path}: not a caviar person detector model")
        return PixelDetector(data["forest"], data["min_pixels"], data["threshold"])


class OnnxPixelModel:
    """A user-supplied ONNX pixel classifier: input (N, 10) float32 features as
    :func:`features` computes them, output per-pixel person probabilities, either
    (N, 2) class probabilities or (N,) / (N, 1) person probabilities. Runs with
    onnxruntime (``pip install caviar-plugins[onnx]``); ``python -m
    caviar_plugins.tools.training.train_detector --export-onnx PATH`` writes the project's detector
    in this form."""

    def __init__(self, path, session=None):
        from caviar_plugins.vision.yolo import onnx_session

        self.session = session if session is not None else onnx_session(path)
        inputs = self.session.get_inputs()
        width = inputs[0].shape[-1] if len(inputs) == 1 and inputs[0].shape else None
        if len(inputs) != 1 or (isinstance(width, int) and width != 10) or len(inputs[0].shape or ()) != 2:
            raise ValueError(f"{path}: expected one input of shape (N, 10), got "
                             f"{[(i.name, i.shape) for i in inputs]}")
        self.input = inputs[0].name

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        for out in reversed(self.session.run(None, {self.input: x.astype(np.float32)})):
            out = np.asarray(out)
            if out.dtype.kind == "f" and out.ndim == 2 and out.shape[1] == 2:
                return out
            if out.dtype.kind == "f" and (out.ndim == 1 or out.shape[-1] == 1):
                p = out.reshape(-1)
                return np.stack([1 - p, p], axis=1)
        raise ValueError("the ONNX model has no output of person probabilities ((N, 2) or (N,))")


def export_onnx(detector: PixelDetector, path: pathlib.Path) -> None:
    from skl2onnx import to_onnx

    model = to_onnx(detector.forest, np.zeros((1, 10), dtype=np.float32),
                    options={id(detector.forest): {"zipmap": False}}, target_opset=17)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(model.SerializeToString())


def frames(count: int, seed: int, loss_rates=(0.0, 0.0, 0.01, 0.25, 0.5), loss: str = "packets"):
    """Rendered frames with labels: half over a target (at random offsets and
    altitudes), half anywhere along the route; each with a random packet loss
    (``loss = "packets"``: the image link's 1400-byte packets; ``"bytes"``: single bytes
    zeroed, the 2023 degradation of ``protocol = "paper"``)."""
    rng = np.random.default_rng(seed)
    visual = VisualScene(VisualConfig(), seed=seed)
    path = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    targets = np.array(visual.cfg.targets)
    for i in range(count):
        if i % 2 == 0:
            xy = targets[rng.integers(len(targets))] + rng.normal(0, 2.5, 2)
        else:
            xy = path.at(rng.uniform(0, path.length))[:2] + rng.normal(0, 3, 2)
        z = rng.uniform(7.0, 12.0)
        image, labels = visual.render_labelled([xy[0], xy[1], z])
        rate = float(rng.choice(loss_rates))
        if rate and loss == "bytes":
            from caviar_plugins.protocol import zero_bytes

            image = zero_bytes(image, rate, rng)
        elif rate:
            image = packet_loss(image, rate, rng)
        yield image, labels, rate


def train(count: int = 240, seed: int = TRAINING_SEED, pixels_per_frame: int = 600,
          loss: str = "packets") -> PixelDetector:
    from sklearn.ensemble import RandomForestClassifier

    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for image, labels, _ in frames(count, seed, loss=loss):
        f = features(image)
        y = (labels.reshape(-1) >= 0).astype(np.int8)
        pos, neg = np.flatnonzero(y), np.flatnonzero(y == 0)
        take = np.concatenate([pos, rng.choice(neg, min(len(neg), pixels_per_frame), replace=False)])
        xs.append(f[take])
        ys.append(y[take])
    forest = RandomForestClassifier(n_estimators=40, max_depth=14, min_samples_leaf=3, n_jobs=1,
                                    random_state=seed, class_weight="balanced")
    forest.fit(np.concatenate(xs), np.concatenate(ys))
    return PixelDetector(forest)


def evaluate(detector: PixelDetector, count: int = 120, seed: int = TRAINING_SEED + 1, min_visible: int = 12,
             loss: str = "packets") -> dict:
    """Object-level precision and recall on frames not seen in training, per loss rate.
    A target counts when at least ``min_visible`` of its pixels are in the frame; a
    detection is correct when its region overlaps a target's pixels."""
    from scipy.ndimage import label

    stats: dict[float, dict[str, int]] = {}
    for image, labels, rate in frames(count, seed, loss=loss):
        s = stats.setdefault(rate, {"tp": 0, "fp": 0, "fn": 0, "frames": 0})
        s["frames"] += 1
        mask, _ = detector.mask(image)
        regions, n = label(mask)
        found = set()
        for k in range(1, n + 1):
            region = regions == k
            if region.sum() < detector.min_pixels:
                continue
            hit = labels[region]
            hit = hit[hit >= 0]
            if len(hit):
                s["tp"] += 1
                found.update(np.unique(hit).tolist())
            else:
                s["fp"] += 1
        visible = [p for p in np.unique(labels[labels >= 0]) if (labels == p).sum() >= min_visible]
        s["fn"] += sum(1 for p in visible if p not in found)
    out = {}
    for rate, s in sorted(stats.items()):
        out[f"{rate:.2f}"] = {**s, "precision": s["tp"] / max(1, s["tp"] + s["fp"]),
                              "recall": (s["tp"] and (s["tp"] / max(1, s["tp"] + s["fn"]))) or 0.0}
    return out


def cache_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("CAVIAR_CACHE", pathlib.Path.home() / ".cache" / "caviar"))


def builtin_model_path(loss: str = "packets") -> pathlib.Path:
    """Where the builtin model is cached (per model version and scikit-learn version;
    ``loss = "bytes"``: the one trained on the 2023 byte-level degradation)."""
    import sklearn

    tag = "" if loss == "packets" else f"-{loss}"
    return cache_dir() / f"person-detector-v{MODEL_VERSION}{tag}-sklearn{sklearn.__version__}.pkl"


def builtin_model(loss: str = "packets") -> PixelDetector:
    """The project's detector, trained on first use and cached. ``loss = "bytes"``:
    trained on frames degraded as in ``protocol = "paper"`` (bytes zeroed), the
    ``builtin-paper`` model."""
    path = builtin_model_path(loss)
    if path.exists():
        try:
            return PixelDetector.load(path)
        except ValueError:
            pass  # unreadable or stale: train again
    detector = train(loss=loss)
    detector.save(path)
    return detector


BUILTIN = {"builtin": "packets", "builtin-paper": "bytes"}
"""Builtin models by name: the degradation they were trained on."""


class YoloPersonDetector:
    """A YOLO ONNX model (:class:`~caviar_plugins.vision.yolo.YoloOnnx`) behind the pixel
    detector's interface: each box is a :class:`Detection` at the box centre."""

    def __init__(self, model):
        self.model = model

    @staticmethod
    def _detections(boxes) -> list[Detection]:
        out = []
        for b in boxes:
            row, col = b.centre
            out.append(Detection(row, col, int(round((b.x1 - b.x0) * (b.y1 - b.y0))), b.score,
                                 (b.x0, b.y0, b.x1, b.y1)))
        return out

    def detect(self, image: np.ndarray) -> list[Detection]:
        return self._detections(self.model.detect(image))

    def detect_many(self, images: list[np.ndarray], pool: ThreadPoolExecutor | None = None,
                    chunks: int = 0) -> list[list[Detection]]:
        # One batch through onnxruntime, whose own threads share the work.
        return [self._detections(found) for found in self.model.detect_many(images)]
