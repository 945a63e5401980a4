"""Person detector for UAV images, trained by the project on its own renders.

No pretrained weights can be downloaded, so the detector is learned from frames the
camera module renders, with exact labels from the renderer (each pixel's shape):
a random forest classifies pixels from their colour and neighbourhood, and
connected regions of person pixels of plausible size are the detections. Training
includes packet-loss-degraded frames, so the detector meets the images it gets in
the loop.

    python -m caviar_plugins.tools.training.train_detector      # trains, evaluates on held-out frames

The ``builtin`` model is trained on first use (about half a minute) and cached under
``$CAVIAR_CACHE`` (default ``~/.cache/caviar``); ``model = "PATH.pkl"`` loads another,
``model = "PATH.onnx"`` a user-supplied ONNX pixel classifier (see :class:`OnnxPixelModel`).

``model = "yolo"`` runs the project's YOLO, trained on the twin's own frames
(``python -m caviar_plugins.tools.training.train_yolo``), with onnxruntime; ``model = "PATH.onnx"``
with an image input runs any YOLOv8/YOLO11-style ONNX detector (:mod:`caviar_plugins.vision.yolo`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections import OrderedDict, defaultdict
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

import caviar
from caviar_plugins.schema import DETECTIONS, IMAGES, POSITIONS, every_ue, read_position, ue_of
from caviar_plugins.torch_device import check_setting

# The models live in pixel_detector; named here too, where users and tests have found them.
from caviar_plugins.vision.pixel_detector import (  # noqa: F401
    BUILTIN,
    MODEL_VERSION,
    TRAINING_SEED,
    Detection,
    OnnxPixelModel,
    PixelDetector,
    YoloPersonDetector,
    assemble_features,
    builtin_model,
    builtin_model_path,
    cache_dir,
    evaluate,
    export_onnx,
    feature_parts,
    features,
    frames,
    train,
    unique_rows,
)


class PersonDetector(caviar.Plugin):
    """Detects people in received images (``ai.images.<UE_Id>``, or camera images
    directly) and publishes ``ai.detections`` with each detection's estimated
    ground position, from the UAV's position and the nadir camera's geometry."""

    subscribe = [every_ue(IMAGES), POSITIONS]
    publishes = (DETECTIONS,)

    @dataclasses.dataclass
    class Params:
        model: str = "builtin"
        """``builtin`` (the pixel classifier trained on packet loss), ``builtin-paper``
        (trained on the 2023 byte-level loss of ``protocol = "paper"``), ``yolo`` (the
        project's YOLO trained on the twin's frames, ONNX) or a model file: ``.pkl`` (a pixel
        classifier), ``.onnx`` taking images (N, 3, H, W) (any YOLOv8/YOLO11-style detector,
        :mod:`caviar_plugins.vision.yolo`) or pixel features (N, 10) (:class:`OnnxPixelModel`)."""
        confidence: float = 0.25
        """YOLO: boxes scored below this are dropped."""
        iou: float = 0.45
        """YOLO: non-maximum suppression's IoU threshold."""
        person_class: int = 0
        """YOLO: the class index of persons (0 in the project's model and in COCO)."""
        fov_deg: float = 70.0
        """Horizontal field of view of the camera (as in the camera module)."""
        workers: int = 0
        """Threads that detect in a step's images side by side; 0 = one per CPU core.
        Each image is classified whole by one thread, so the detections do not depend on
        this number. Only parts of the work release the GIL (the forest's tree walk): 16
        threads measured 1.4x one at 20 UAVs. With ``batch = true`` the threads detect
        batches of images (two per thread)."""
        batch: bool = True
        """Classify a step's images in batches (:meth:`PixelDetector.detect_many`, one
        batch per half of ``workers``' share, side by side; the same detections, ~4x
        faster at 50 UAVs, and ~2x for one UAV: only its distinct feature rows are
        classified); ``false``: image by image on ``workers`` threads, as before issue #18."""
        runtime: str = "auto"
        """``auto`` (torch for the project's own models where it sees a GPU, else the model's
        CPU runtime; a user's file keeps its CPU runtime), ``onnxruntime``
        (the CPU runtime: onnxruntime for ONNX files, scikit-learn for the builtin forests) or
        ``torch`` on ``device``: YOLO's ONNX graph run by PyTorch (a step's images in one batch,
        a CUDA graph on a GPU; :mod:`caviar_plugins.vision.onnx_torch`, the same boxes within
        float32 rounding), the builtin forests walked by torch
        (:mod:`caviar_plugins.vision.forest_torch`, bit for bit the same probabilities)."""
        device: str = "auto"
        """Where torch runs the model: ``auto`` (the first GPU, else the host), ``cpu``, ``cuda`` or ``cuda:N``."""
        seen_images: int = 8
        """An image the same as one of the last ``seen_images`` distinct images of its UE,
        bit for bit, gets that image's detections without the model (it would find the
        same; a hovering UAV's frames that lost no packet are all alike); 0 = every image
        through the model."""

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        if p.workers < 0:
            raise ValueError(f"params.workers = {p.workers}: expected 0 (one per CPU core) or more")
        if not 0.0 <= p.confidence <= 1.0:
            raise ValueError(f"params.confidence = {p.confidence}: expected a score between 0 and 1")
        if not 0.0 < p.iou <= 1.0:
            raise ValueError(f"params.iou = {p.iou}: expected an IoU in (0, 1]")
        if p.person_class < 0:
            raise ValueError(f"params.person_class = {p.person_class}: expected a class index (0 or more)")
        if p.seen_images < 0:
            raise ValueError(f"params.seen_images = {p.seen_images}: expected a count (0 or more)")
        from caviar_plugins.vision.yolo import choose_runtime

        try:
            runtime = choose_runtime(p.runtime, check_setting(p.device))
        except ValueError as e:  # ("device: expected ...", "runtime = 'x': expected ...")
            raise ValueError(f"params.{e}") from None
        from caviar_plugins.vision.runtimes import detector_model

        self.detector: PixelDetector | YoloPersonDetector = detector_model(ctx, runtime)
        self.positions: dict[str, np.ndarray] = {}
        # UE -> image digest -> detections, oldest first
        self.seen: defaultdict[str, OrderedDict[bytes, list]] = defaultdict(OrderedDict)
        self.workers = p.workers or os.cpu_count() or 1
        self.pool = ThreadPoolExecutor(self.workers, thread_name_prefix="detector") if self.workers > 1 else None

    def teardown(self):
        if self.pool is not None:
            self.pool.shutdown()

    def state(self):
        # The model and the threads come from setup; the last known positions are the state.
        return {"positions": self.positions}

    def restore(self, state):
        self.positions = state["positions"]

    def step(self, t, inbox):
        for m in inbox.on(POSITIONS):
            self.positions[m.data["UE_Id"]] = read_position(m.data)
        images = list(inbox.on(every_ue(IMAGES)))
        keep = self.ctx.params.seen_images
        keys = [_digest(m.data) if keep else b"" for m in images]
        known = [self.seen[ue_of(m.topic)].get(k) if keep else None for m, k in zip(images, keys, strict=True)]
        todo = [m for m, found in zip(images, known, strict=True) if found is None]
        if self.ctx.params.batch and todo:  # one image too: its distinct feature rows only
            fresh = self.detector.detect_many([m.data for m in todo], pool=self.pool, chunks=2 * self.workers)
        elif self.pool is not None and len(todo) > 1:
            fresh = list(self.pool.map(lambda m: self.detector.detect(m.data), todo))
        else:
            fresh = [self.detector.detect(m.data) for m in todo]
        results, new = [], iter(fresh)
        for m, key, found in zip(images, keys, known, strict=True):
            if found is None:
                found = next(new)
                if keep:
                    memo = self.seen[ue_of(m.topic)]
                    memo[key] = found
                    while len(memo) > keep:
                        memo.popitem(last=False)
            results.append(found)
        for m, detections in zip(images, results, strict=True):
            ue = ue_of(m.topic)
            image = m.data
            pos = self.positions.get(ue)
            found = []
            for d in detections:
                item: dict[str, Any] = {"row": d.row, "col": d.col, "pixels": d.pixels, "score": round(d.score, 4)}
                if d.box is not None:
                    item["box"] = [round(v, 2) for v in d.box]
                if pos is not None:
                    item["ground"] = pixel_to_ground(d.row, d.col, image.shape, pos, self.ctx.params.fov_deg)
                found.append(item)
            yield DETECTIONS, {"UE_Id": ue, "image_step": m.step, "count": len(found), "detections": found}


def _digest(image: np.ndarray) -> bytes:
    """An image's identity for :attr:`PersonDetector.Params.seen_images`: its shape, type
    and bytes, hashed."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((image.shape, image.dtype.str)).encode())
    h.update(np.ascontiguousarray(image).data)
    return h.digest()


def pixel_to_ground(row: float, col: float, shape, position, fov_deg: float) -> dict:
    """Ground point (z = 0) seen at a pixel of a nadir camera at ``position`` (x, y, z)
    with image-up = +y."""
    h, w = shape[:2]
    x, y, z = (float(v) for v in position)
    half = z * math.tan(math.radians(fov_deg) / 2)  # half the footprint width
    metres_per_px = 2 * half / w
    dx = (col + 0.5 - w / 2) * metres_per_px
    dy = (h / 2 - row - 0.5) * metres_per_px
    return {"x": x + X_SIGN * dx, "y": y + dy}


# Whether image columns grow with +x or -x (Mitsuba's look_at with up = +y looking
# down); checked by tests/test_sar.py against a rendered target.
X_SIGN = 1.0

