"""Trains the project's YOLO person detector from scratch on the twin's own frames.

    python -m caviar_plugins.tools.training.train_yolo [--epochs 40] [--work runs/yolo] [--out PATH.onnx]

1. renders the frames and their labels (:mod:`caviar_plugins.tools.training.twin_frames`) into
   ``WORK/frames`` unless they are there;
2. trains Ultralytics YOLO from ``data/person-yolo.yaml`` (YOLOv8's blocks at 1/4 width with
   heads at strides 4, 8 and 16, one class,
   no pretrained weights) on CPU with a fixed seed and deterministic kernels, with
   Ultralytics' progress bars;
3. exports the best epoch to ONNX (opset 17, input 1 x 3 x 128 x 160: the camera's 160 x 120
   letterboxed) and copies it to ``--out`` (default: the builtin model,
   ``caviar_plugins/data/person-yolo.onnx``);
4. scores it and today's pixel classifier on the held-out test frames per packet-loss level
   (:mod:`caviar_plugins.tools.training.yolo_eval`) and writes ``--report`` (JSON, with a Markdown
   table and a plot beside it).

Training needs ``pip install 'caviar-plugins[yolo]'`` (Ultralytics, torch); running the
model needs only onnxruntime.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import time

from caviar_plugins.assets import DATA
from caviar_plugins.vision.yolo import BUILTIN_YOLO

MODEL_YAML = DATA / "person-yolo.yaml"
IMGSZ = 160
EXPORT_SIZE = (128, 160)


DEGREES = 0.0
"""Ultralytics' rotation augmentation (±degrees). None: a nadir camera sees persons at any
heading already (the frames' flights go every way), and a rotated frame's boxes are the
rotated box's axis-aligned hull (``ultralytics.data.augment.RandomPerspective.apply_bboxes``
transforms the 4 corners and takes their min/max): at 45° a square box grows by √2 (41 %) a
side over the rotated person's own box. Training on them teaches loose boxes, which mAP@0.5
counts as misses. The first model
(``degrees = 180``) scored 0.555 on the shaded test frames."""


def train(frames: pathlib.Path, work: pathlib.Path, epochs: int, seed: int, batch: int = 32, imgsz: int = IMGSZ,
          model_yaml: pathlib.Path = MODEL_YAML, workers: int = 2, patience: int = 100,
          degrees: float = DEGREES) -> pathlib.Path:
    """Trains and returns the path of the best weights (``.pt``)."""
    os.environ.setdefault("YOLO_OFFLINE", "true")  # no update checks, no downloads
    from ultralytics import YOLO

    model = YOLO(str(model_yaml), task="detect")
    model.train(data=str(frames / "data.yaml"), epochs=epochs, imgsz=imgsz, batch=batch, device="cpu",
                workers=workers, seed=seed, deterministic=True, pretrained=False, amp=False, plots=False,
                project=str(work.resolve()), name="train", exist_ok=True, patience=patience, verbose=False,
                cache=True, fliplr=0.5, flipud=0.5, degrees=degrees, scale=0.25, close_mosaic=max(1, epochs // 6))
    best = work / "train" / "weights" / "best.pt"
    if not best.exists():
        raise RuntimeError(f"training wrote no {best}")
    return best


def export(weights: pathlib.Path, out: pathlib.Path, size=EXPORT_SIZE) -> pathlib.Path:
    """The weights as ONNX (opset 17, fixed input 1 x 3 x H x W), copied to ``out``."""
    os.environ.setdefault("YOLO_OFFLINE", "true")
    from ultralytics import YOLO

    exported = pathlib.Path(YOLO(str(weights)).export(format="onnx", imgsz=list(size), opset=17, simplify=False,
                                                       dynamic=False, device="cpu"))
    out.parent.mkdir(parents=True, exist_ok=True)
    if exported.resolve() != out.resolve():
        shutil.copyfile(exported, out)
    return out


def write_report(report: dict, path: pathlib.Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
    rows = ["| frames | packet loss | YOLO mAP@0.5 | YOLO P / R (conf 0.25) | pixel forest mAP@0.5 "
            "| pixel forest P / R |", "|---|---:|---:|---:|---:|---:|"]
    for name, scores in (("twin test (shaded)", report["scores"]), ("camera (flat, the loop's)",
                                                                    report.get("camera_frames", {}).get("scores"))):
        if not scores:
            continue
        yolo, strict, forest = scores["yolo"], scores["yolo_at_0.25"], scores["pixel_forest"]
        for level in yolo:
            rows.append(f"| {name} | {float(level):.0%} | {yolo[level]['ap50']:.3f} | {strict[level]['precision']:.3f}"
                        f" / {strict[level]['recall']:.3f} | {forest[level]['ap50']:.3f} | "
                        f"{forest[level]['precision']:.3f} / {forest[level]['recall']:.3f} |")
    path.with_suffix(".md").write_text("\n".join(rows) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for name, scores, style in (("twin test", report["scores"], "-"),
                                ("camera", report.get("camera_frames", {}).get("scores"), ":")):
        if not scores:
            continue
        levels = [float(v) * 100 for v in scores["yolo"]]
        ax.plot(levels, [v["ap50"] for v in scores["yolo"].values()], "o" + style, color="C0",
                label=f"YOLO (twin-trained, ONNX), {name} frames")
        ax.plot(levels, [v["ap50"] for v in scores["pixel_forest"].values()], "s" + style, color="C1",
                label=f"pixel forest (today's), {name} frames")
    ax.set_xlabel("packet loss (%)")
    ax.set_ylabel("mAP@0.5 (held-out frames)")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path.with_suffix(".png"), dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.training.train_yolo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=pathlib.Path, default=pathlib.Path("runs/yolo"))
    ap.add_argument("--train-frames", type=int, default=1200)
    ap.add_argument("--val-frames", type=int, default=240)
    ap.add_argument("--test-frames", type=int, default=240)
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--degrees", type=float, default=DEGREES,
                    help="Ultralytics' rotation augmentation, ± degrees (default 0: see DEGREES)")
    ap.add_argument("--out", type=pathlib.Path, default=BUILTIN_YOLO)
    ap.add_argument("--report", type=pathlib.Path, default=pathlib.Path("docs/results/yolo.json"))
    ap.add_argument("--score-only", action="store_true",
                    help="train nothing: score --out on the test frames and write the report")
    ap.add_argument("--train-s", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from caviar_plugins.tools.training.twin_frames import write_dataset
    from caviar_plugins.tools.training.yolo_eval import (
        camera_frames,
        evaluate,
        held_out_frames,
        pixel_detect,
        yolo_detect,
    )
    from caviar_plugins.vision.person_detector import builtin_model
    from caviar_plugins.vision.yolo import YoloOnnx

    frames = args.work / "frames"
    if not (frames / "data.yaml").exists():
        write_dataset(frames, {"train": args.train_frames, "val": args.val_frames, "test": args.test_frames})
    meta = json.loads((frames / "meta.json").read_text())
    if args.score_only:
        onnx, train_s = args.out, args.train_s
    else:
        t0 = time.perf_counter()
        best = train(frames, args.work, args.epochs, args.seed, batch=args.batch, degrees=args.degrees)
        train_s = time.perf_counter() - t0
        onnx = export(best, args.out)
    images, truths = held_out_frames(frames)
    scores = {"yolo": evaluate(yolo_detect(YoloOnnx(onnx, confidence=0.001)), images, truths),
              "yolo_at_0.25": evaluate(yolo_detect(YoloOnnx(onnx)), images, truths),
              "pixel_forest": evaluate(pixel_detect(builtin_model()), images, truths)}
    # The loop's own frames: the camera plugin's flat colours, which neither saw in training (the
    # forest was trained on frames like them, from other seeds).
    flat_images, flat_truths = camera_frames()
    flat = {"yolo": evaluate(yolo_detect(YoloOnnx(onnx, confidence=0.001)), flat_images, flat_truths),
            "yolo_at_0.25": evaluate(yolo_detect(YoloOnnx(onnx)), flat_images, flat_truths),
            "pixel_forest": evaluate(pixel_detect(builtin_model()), flat_images, flat_truths)}
    shown = [a for a in (argv or []) if a != "--score-only" and not a.startswith("--train-s")]
    report = {"command": " ".join(["python -m caviar_plugins.tools.training.train_yolo", *shown]),
              "model_yaml": MODEL_YAML.name, "epochs": args.epochs, "seed": args.seed, "imgsz": IMGSZ,
              "degrees": args.degrees,
              "shaded_test_map50": round(scores["yolo"]["0.00"]["ap50"], 4),
              "export_input": list(EXPORT_SIZE), "train_s": train_s and round(train_s, 1),
              "onnx_bytes": onnx.stat().st_size,
              "frames": meta, "scores": scores, "camera_frames": {"frames": len(flat_images), "scores": flat}}
    write_report(report, args.report)
    print(args.report.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
