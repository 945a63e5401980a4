"""YOLO person detection from an ONNX file, with onnxruntime, or with torch on its device.

Any YOLOv8 / YOLO11-style detector exported to ONNX (Ultralytics' ``model.export(format=
"onnx")``, or one trained on real drone footage) runs here. What is read from the file:

* **input**: one tensor ``(N, 3, H, W)`` float32, RGB scaled to 0-1. ``H`` and ``W`` are
  taken from the file (or from Ultralytics' ``imgsz`` metadata when they are dynamic; else
  ``imgsz`` of :class:`YoloOnnx`). An image is letterboxed into it as Ultralytics does:
  scaled to fit, keeping its aspect, centred, padded with grey 114.
* **output** (the first), one of two layouts:

  - *raw* (YOLOv8, YOLO11): ``(N, 4 + C, A)`` (or its transpose ``(N, A, 4 + C)``, told apart
    by A > 4 + C, as in any real model): for each
    of A anchors the box centre x, y, width, height in input pixels, then C class scores
    (already sigmoid). Boxes above ``confidence`` for the person class go through
    non-maximum suppression (IoU ``iou``) here.
  - *end-to-end* (YOLOv10, or ``nms=True`` exports): ``(N, K, 6)``: x0, y0, x1, y1, score,
    class, already suppressed.

``person_class`` picks the class (0: the project's models, and COCO's "person"). Boxes are
mapped back to image pixels. Lost packets arrive as black (zero) pixels: the project's model
was trained with them (:mod:`caviar_plugins.tools.training.twin_frames`).
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Any

import numpy as np

from caviar_plugins.assets import DATA

BUILTIN_YOLO = DATA / "person-yolo.onnx"
"""The project's YOLO, trained on the twin's frames (``python -m caviar_plugins.tools.training.train_yolo``)."""


@dataclasses.dataclass
class Box:
    x0: float
    y0: float
    x1: float
    y1: float
    score: float

    @property
    def centre(self) -> tuple[float, float]:
        """(row, col) of the box centre, in pixel coordinates (pixel i spans [i, i + 1))."""
        return (self.y0 + self.y1) / 2 - 0.5, (self.x0 + self.x1) / 2 - 0.5


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of boxes ``a`` (n, 4) and ``b`` (m, 4), as (n, m); x0, y0, x1, y1."""
    a, b = np.asarray(a, dtype=float).reshape(-1, 4), np.asarray(b, dtype=float).reshape(-1, 4)
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
    area_a = np.prod(a[:, 2:] - a[:, :2], axis=1)
    area_b = np.prod(b[:, 2:] - b[:, :2], axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def nms(boxes: np.ndarray, scores: np.ndarray, threshold: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, best first."""
    order = np.argsort(-scores, kind="stable")
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        if len(order) == 1:
            break
        rest = order[1:]
        order = rest[iou(boxes[i:i + 1], boxes[rest])[0] <= threshold]
    return np.array(keep, dtype=np.int64)


def execution_providers(available: list[str], gpu: bool) -> tuple[list[str], str | None]:
    """onnxruntime's providers for a session, and the one line to print about them (None:
    nothing to say): CUDA first where onnxruntime has it (``onnxruntime-gpu``), else the CPU,
    said once when an NVIDIA GPU is there to use."""
    if "CUDAExecutionProvider" in available:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"], None
    note = ("onnxruntime has no CUDA provider (install onnxruntime-gpu to use the GPU): ONNX models run on "
            "the CPU") if gpu else None
    return ["CPUExecutionProvider"], note


_SAID: set[str] = set()


def onnx_session(path, threads: int = 0, what: str = "ONNX model"):
    """An onnxruntime session of the ONNX file at ``path`` (on the GPU where onnxruntime has
    its CUDA provider, see :func:`execution_providers`); a clear error naming the file when it
    is missing, cannot be loaded or onnxruntime is not installed."""
    path = pathlib.Path(path)
    try:
        import onnxruntime as ort
    except ImportError:
        raise ValueError(f"{path}: ONNX models need onnxruntime (pip install 'caviar-plugins[onnx]')") from None
    if not path.is_file():
        raise ValueError(f"{path}: no such {what} file")
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    from caviar._gpu import open_sampler

    providers, note = execution_providers(list(ort.get_available_providers()), gpu=open_sampler() is not None)
    if note is not None and note not in _SAID:
        _SAID.add(note)
        print(note, file=sys.stderr, flush=True)
    try:
        return ort.InferenceSession(str(path), options, providers=providers)
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"{path}: cannot load the ONNX model: {e}") from None


def takes_images(session) -> bool:
    """Whether an ONNX session's model takes images (N, 3, H, W): a detector such as YOLO,
    not a pixel classifier."""
    inputs = session.get_inputs()
    return len(inputs) == 1 and len(inputs[0].shape) == 4


RUNTIMES = ("auto", "onnxruntime", "torch")
"""How a YOLO file runs: ``onnxruntime`` (its CUDA provider where installed, else the CPU),
``torch`` (the graph through PyTorch on torch's device, :mod:`caviar_plugins.vision.onnx_torch`)
or ``auto``: torch where it sees a GPU, else onnxruntime."""


def torch_sees_gpu() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def choose_runtime(runtime: str, device: str = "auto") -> str:
    """``onnxruntime`` or ``torch`` for a ``runtime`` setting (:data:`RUNTIMES`) and torch
    ``device`` setting (a device named other than ``auto`` means torch)."""
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime = {runtime!r}: expected one of {', '.join(RUNTIMES)}")
    if runtime == "auto":
        return "torch" if device != "auto" or torch_sees_gpu() else "onnxruntime"
    return runtime


def torch_device_of(device: str = "auto"):
    """The ``torch.device`` YOLO runs on: ``auto`` is the first GPU where torch sees one, else the host."""
    import torch

    from caviar_plugins.torch_device import check_setting, gpu_or_host, is_cuda

    check_setting(device)
    if device == "auto":
        return gpu_or_host()
    if is_cuda(device) and not torch.cuda.is_available():
        raise ValueError(f"device = {device!r}: torch sees no CUDA GPU here (use 'auto' or the host)")
    return torch.device(device)


class YoloOnnx:
    """A YOLO detector in an ONNX file (layouts in the module's text); ``session``: the file
    already loaded (:func:`onnx_session`). ``runtime``: ``onnxruntime`` (the default here) or
    ``torch`` on ``device`` (:data:`RUNTIMES`; :class:`~caviar_plugins.vision.onnx_torch.TorchGraph`:
    the whole batch in one run, on the GPU as a CUDA graph); both find the same boxes, within
    float32 rounding on the CPU (``tests/test_yolo_torch.py``)."""

    def __init__(self, path, confidence: float = 0.25, iou_threshold: float = 0.45, person_class: int = 0,
                 imgsz: tuple[int, int] | None = None, threads: int = 0, session=None,
                 runtime: str = "onnxruntime", device: str = "auto"):
        path = pathlib.Path(path)
        if person_class < 0:
            raise ValueError(f"{path}: person_class = {person_class}: expected a class index (0 or more)")
        if not 0.0 <= confidence <= 1.0:
            raise ValueError(f"{path}: confidence = {confidence}: expected a score between 0 and 1")
        self.runtime = choose_runtime(runtime, device)
        self.session: Any = None
        self.graph: Any = None
        if self.runtime == "torch":
            from caviar_plugins.vision.onnx_torch import TorchGraph

            self.graph = TorchGraph(path, torch_device_of(device))
            self.input, input_shape = self.graph.input, self.graph.input_shape
            output_shape, output_name = self.graph.output_shape, self.graph.output
            meta = self.graph.metadata
        else:
            self.session = session if session is not None else onnx_session(path, threads, "YOLO ONNX")
            inputs = self.session.get_inputs()
            if len(inputs) != 1:
                raise ValueError(f"{path}: expected one image input (N, 3, H, W), got "
                                 f"{[(i.name, i.shape) for i in inputs]}")
            self.input, input_shape = inputs[0].name, list(inputs[0].shape)
            output_shape, output_name = self.session.get_outputs()[0].shape, self.session.get_outputs()[0].name
            meta = self.session.get_modelmeta().custom_metadata_map
        if len(input_shape) != 4 or input_shape[1] not in (3, "3", None) and not isinstance(input_shape[1], str):
            raise ValueError(f"{path}: expected one image input (N, 3, H, W), got {self.input} {input_shape}")
        self.batch = input_shape[0] if isinstance(input_shape[0], int) else None
        h, w = input_shape[2:]
        if not (isinstance(h, int) and isinstance(w, int)):
            if imgsz is None and "imgsz" in meta:
                imgsz = tuple(int(v) for v in meta["imgsz"].strip("[]() ").split(","))  # type: ignore[assignment]
            if imgsz is None:
                raise ValueError(f"{path}: the input size is dynamic ({input_shape}) and the file has no "
                                 "'imgsz' metadata: give imgsz = [H, W]")
            h, w = imgsz
        self.size = (int(h), int(w))
        if len(output_shape) != 3:
            raise ValueError(f"{path}: expected a detection output (N, 4 + classes, anchors) or (N, K, 6), got "
                             f"{output_name} {output_shape}")
        self.path = path
        self.confidence, self.iou_threshold, self.person_class = confidence, iou_threshold, person_class
        self.names = meta.get("names", "")

    def run(self, batch: np.ndarray) -> np.ndarray:
        """The model's first output for ``batch`` (N, 3, H, W) float32, as numpy."""
        if self.graph is not None:  # (any batch size: see onnx_torch)
            from caviar_plugins.torch_device import to_numpy

            return to_numpy(self.graph(batch))
        fixed = self.batch
        if fixed is not None and fixed != len(batch):  # a batch size baked into the file
            pad = -len(batch) % fixed  # the last chunk filled with grey frames, their outputs dropped
            padded = np.concatenate([batch, np.full((pad, *batch.shape[1:]), 114 / 255.0, dtype=np.float32)])
            outs = [self.session.run(None, {self.input: padded[i:i + fixed]})[0] for i in range(0, len(padded), fixed)]
            return np.concatenate(outs)[:len(batch)]
        return self.session.run(None, {self.input: batch})[0]

    def letterbox(self, image: np.ndarray) -> tuple[np.ndarray, float, tuple[float, float]]:
        """The model's input for ``image`` (H, W, 3 uint8), the scale and the (x, y) padding."""
        h, w = image.shape[:2]
        th, tw = self.size
        r = min(th / h, tw / w)
        nh, nw = round(h * r), round(w * r)
        if (nh, nw) != (h, w):
            from PIL import Image

            image = np.asarray(Image.fromarray(image).resize((nw, nh), Image.Resampling.BILINEAR))
        top, left = (th - nh) // 2, (tw - nw) // 2
        canvas = np.full((th, tw, 3), 114, dtype=np.uint8)
        canvas[top:top + nh, left:left + nw] = image
        return canvas, r, (float(left), float(top))

    def detect_many(self, images: list[np.ndarray]) -> list[list[Box]]:
        """The person boxes in each image (image pixels), best first."""
        if not images:
            return []
        prepared = [self.letterbox(im) for im in images]
        batch = np.stack([p[0] for p in prepared]).transpose(0, 3, 1, 2).astype(np.float32) / 255.0
        raw = self.run(batch)
        result = []
        for i, (_, r, (left, top)) in enumerate(prepared):
            boxes, scores = self._decode(np.asarray(raw[i], dtype=np.float32))
            h, w = images[i].shape[:2]
            boxes = (boxes - [left, top, left, top]) / r
            boxes = np.clip(boxes, 0, [w, h, w, h])
            result.append([Box(float(b[0]), float(b[1]), float(b[2]), float(b[3]), float(s))
                           for b, s in zip(boxes, scores, strict=True)])
        return result

    def detect(self, image: np.ndarray) -> list[Box]:
        return self.detect_many([image])[0]

    def _decode(self, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (x0, y0, x1, y1, input pixels) and scores of one image's output."""
        if out.shape[-1] == 6 and out.shape[0] != 6:  # end-to-end: (K, 6)
            # (rows of score 0 are the padding of a fixed K)
            keep = (out[:, 4] >= self.confidence) & (out[:, 4] > 0) & (np.rint(out[:, 5]) == self.person_class)
            return out[keep, :4], out[keep, 4]
        if out.shape[0] > out.shape[1]:  # (A, 4 + C): transposed raw (a model has more anchors than classes)
            out = out.T
        if out.shape[0] < 5 + self.person_class:
            raise ValueError(f"{self.path}: the output has {out.shape[0] - 4} classes; person_class = "
                             f"{self.person_class} is not one of them")
        scores = out[4 + self.person_class]
        keep = scores >= self.confidence
        cx, cy, bw, bh = out[:4, keep]
        boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], axis=1)
        scores = scores[keep]
        kept = nms(boxes, scores, self.iou_threshold)
        return boxes[kept], scores[kept]


def average_precision(detections: list[tuple[np.ndarray, np.ndarray]], truths: list[np.ndarray],
                      threshold: float = 0.5) -> dict:
    """AP at IoU ``threshold`` over images: ``detections`` per image (boxes (n, 4), scores (n,)),
    ``truths`` per image (boxes (m, 4)). A detection is a true positive if it overlaps a
    not yet matched true box by at least the threshold (the best such, images' detections in
    descending score); AP is the area under the precision envelope (all points, as in
    VOC 2010+ and COCO without its 101-point sampling). Also precision and recall over all
    detections kept (those at or above the detector's own confidence threshold)."""
    scored = []  # (score, is true positive)
    total = int(sum(len(t) for t in truths))
    for (boxes, scores), truth in zip(detections, truths, strict=True):
        boxes, scores = np.asarray(boxes, dtype=float).reshape(-1, 4), np.asarray(scores, dtype=float).reshape(-1)
        truth = np.asarray(truth, dtype=float).reshape(-1, 4)
        matched = np.zeros(len(truth), dtype=bool)
        overlap = iou(boxes, truth) if len(truth) else np.zeros((len(boxes), 0))
        for i in np.argsort(-scores, kind="stable"):
            hit = False
            if len(truth):
                cand = np.where(~matched, overlap[i], -1.0)
                j = int(np.argmax(cand))
                if cand[j] >= threshold:
                    matched[j] = hit = True
            scored.append((float(scores[i]), hit))
    scored.sort(key=lambda x: -x[0])
    hits = np.array([s[1] for s in scored], dtype=bool)
    tp, fp = np.cumsum(hits), np.cumsum(~hits)
    recall = tp / total if total else np.zeros(len(tp))
    precision = tp / np.maximum(tp + fp, 1)
    # All-point interpolation: precision made monotone from the right, integrated over recall.
    r = np.concatenate([[0.0], recall, [recall[-1] if len(recall) else 0.0]])
    p = np.concatenate([[1.0], precision, [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]
    ap = float(np.sum((r[1:] - r[:-1]) * p[1:]))
    n_tp = int(tp[-1]) if len(tp) else 0
    n_fp = int(fp[-1]) if len(fp) else 0
    return {"ap50" if threshold == 0.5 else f"ap{int(threshold * 100)}": ap, "tp": n_tp, "fp": n_fp,
            "fn": total - n_tp, "truths": total, "precision": n_tp / max(1, n_tp + n_fp),
            "recall": n_tp / total if total else 0.0}
