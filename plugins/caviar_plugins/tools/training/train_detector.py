"""Trains the person detector on rendered frames and evaluates it on held-out ones.

    python -m caviar_plugins.tools.training.train_detector [--frames 240] [--report docs/results/detector.json]
    python -m caviar_plugins.tools.training.train_detector --export-onnx person-detector.onnx

By default the model replaces the builtin one in the cache (``$CAVIAR_CACHE``, default
``~/.cache/caviar``); ``--out PATH.pkl`` writes it elsewhere (``model = "PATH.pkl"`` of
the ``person-detector`` plugin). ``--export-onnx`` trains nothing: it writes the builtin
model (trained on first use) as an ONNX pixel classifier.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from caviar_plugins.vision.person_detector import builtin_model, builtin_model_path, evaluate, export_onnx, train


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.training.train_detector", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=240, help="training frames (default 240)")
    ap.add_argument("--eval-frames", type=int, default=120, help="held-out evaluation frames (default 120)")
    ap.add_argument("--out", type=pathlib.Path, default=None, help="model file (default: the builtin cache)")
    ap.add_argument("--report", type=pathlib.Path, default=pathlib.Path("docs/results/detector.json"),
                    help="precision and recall per packet-loss rate, JSON")
    ap.add_argument("--export-onnx", type=pathlib.Path, default=None, metavar="PATH",
                    help="write the builtin model as ONNX to PATH instead of training")
    return ap.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.export_onnx is not None:
        export_onnx(builtin_model(), args.export_onnx)
        print(f"model: {args.export_onnx}")
        return
    detector = train(args.frames)
    out = args.out or builtin_model_path()
    detector.save(out)
    report = {"training_frames": args.frames, "eval_frames": args.eval_frames,
              "by_loss_rate": evaluate(detector, args.eval_frames)}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(json.dumps(report, indent=2) + "\n")
    print(f"model: {out}")
    print("| packet loss | frames | precision | recall |\n|---:|---:|---:|---:|")
    for rate, s in report["by_loss_rate"].items():
        print(f"| {float(rate):.0%} | {s['frames']} | {s['precision']:.3f} | {s['recall']:.3f} |")


if __name__ == "__main__":
    main()
