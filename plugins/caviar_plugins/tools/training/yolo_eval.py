"""Person detectors scored on the twin's held-out test frames, per packet-loss level.

Every test frame (:mod:`caviar_plugins.tools.training.twin_frames`, its own scene and flights) is
sent through the image link at each loss level of the paper's table (0, 1 %, 25 %, 50 %;
the same frames at every level, each level's packets drawn from its own seeded generator),
and each detector's boxes are scored against the renderer's boxes: AP at IoU 0.5 (mAP@0.5,
one class), and precision and recall of the boxes a detector reports. The pixel
classifier's boxes are its regions' bounding boxes, scored by their mean probability.

    python -m caviar_plugins.tools.training.yolo_eval DATASET [--model PATH.onnx] [--report OUT.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from caviar_plugins.tools.training.twin_frames import read_labels
from caviar_plugins.vision.image_link import packet_loss
from caviar_plugins.vision.yolo import BUILTIN_YOLO, YoloOnnx, average_precision

LOSS_LEVELS = (0.0, 0.01, 0.25, 0.5)


def held_out_frames(dataset: pathlib.Path, split: str = "test", limit: int = 0) -> tuple[list[np.ndarray],
                                                                                     list[np.ndarray]]:
    from PIL import Image

    images, truths = [], []
    files = sorted((pathlib.Path(dataset) / "images" / split).glob("*.png"))
    for path in files[:limit or None]:
        image = np.asarray(Image.open(path).convert("RGB"))
        images.append(image)
        truths.append(read_labels(pathlib.Path(dataset) / "labels" / split / f"{path.stem}.txt",
                                  image.shape[1], image.shape[0]))
    if not images:
        raise ValueError(f"{dataset}: no {split} frames under images/{split}")
    return images, truths


def camera_frames(count: int = 120, seed: int = 1235) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The camera plugin's own flat-colour frames, as the detector meets them in the SAR loop:
    the pixel forest's held-out frames (:func:`~caviar_plugins.vision.person_detector.frames`,
    seed 1235 as in ``docs/results/detector.json``) without their packet loss, each person's box
    from the renderer's labels."""
    from caviar_plugins.tools.training.twin_frames import yolo_boxes
    from caviar_plugins.vision.person_detector import frames

    images, truths = [], []
    for image, labels, _ in frames(count, seed, loss_rates=(0.0,)):
        images.append(image)
        truths.append(np.array([b[1:] for b in yolo_boxes(labels, 1)], dtype=float).reshape(-1, 4))
    return images, truths


def pixel_boxes(detector, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel classifier's detections as boxes (its regions' bounding boxes) and scores."""
    found = detector.detect(image, boxes=True)
    return (np.array([d.box for d in found], dtype=float).reshape(-1, 4),
            np.array([d.score for d in found], dtype=float))


def evaluate(detect, images: list[np.ndarray], truths: list[np.ndarray], levels=LOSS_LEVELS,
             seed: int = 7) -> dict[str, dict]:
    """``detect(images) -> [(boxes, scores)]`` scored at each loss level."""
    out = {}
    for i, rate in enumerate(levels):
        rng = np.random.default_rng([seed, i])
        seen = [packet_loss(im, rate, rng) if rate else im for im in images]
        out[f"{rate:.2f}"] = {**average_precision(detect(seen), truths), "frames": len(images)}
    return out


def yolo_detect(model: YoloOnnx):
    def detect(images):
        found = model.detect_many(images)
        return [(np.array([[b.x0, b.y0, b.x1, b.y1] for b in f], dtype=float).reshape(-1, 4),
                 np.array([b.score for b in f], dtype=float)) for f in found]
    return detect


def pixel_detect(detector):
    def detect(images):
        return [pixel_boxes(detector, im) for im in images]
    return detect


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.training.yolo_eval", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=pathlib.Path)
    ap.add_argument("--model", type=pathlib.Path, default=BUILTIN_YOLO)
    ap.add_argument("--report", type=pathlib.Path, default=None)
    args = ap.parse_args(argv)
    from caviar_plugins.vision.person_detector import builtin_model

    images, truths = held_out_frames(args.dataset)
    # The detector's own threshold for precision and recall; AP needs the low-score boxes too.
    report = {"yolo": evaluate(yolo_detect(YoloOnnx(args.model, confidence=0.001)), images, truths),
              "yolo_at_0.25": evaluate(yolo_detect(YoloOnnx(args.model)), images, truths),
              "pixel_forest": evaluate(pixel_detect(builtin_model()), images, truths)}
    text = json.dumps(report, indent=2)
    if args.report:
        args.report.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
