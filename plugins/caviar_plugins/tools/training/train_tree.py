"""Fits the beam-selection decision tree on the NLOS samples of dataset runs and writes
the paper's top-K table (JSON, Markdown, plot).

    python -m caviar_plugins.tools.training.train_tree --train runs/beam-dataset \\
        --test runs/beam-test-flight --out models/beam-tree.pkl --report-dir docs/results

The runs come from ``blueprints/beam-dataset`` (``config.toml``: training flights,
``test-flight.toml``: the separate test flight). The NLOS training samples are split
70/30 into fit and validation sets.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from caviar_plugins.beam_selection.dataset import load
from caviar_plugins.beam_selection.decision_tree import K_VALUES, MAX_DEPTH, full_scores, save, top_k_accuracy, train

PAIRS = 256


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.training.train_tree", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", nargs="+", required=True, help="run directories of the dataset blueprint")
    ap.add_argument("--test", required=True, help="run directory of a separate test flight")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("models/beam-tree.pkl"))
    ap.add_argument("--report-dir", type=pathlib.Path, default=pathlib.Path("docs/results"))
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args(argv)


def nlos(data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Positions and best pairs of the NLOS samples."""
    keep = ~data["los"].astype(bool)
    return data["position"][keep], data["best_pair"][keep]


def fit_and_score(train_set: dict, test_set: dict, seed: int):
    """The tree, the sizes of its sets and its top-K accuracy on validation and test."""
    x, y = nlos(train_set)
    order = np.random.default_rng(seed).permutation(len(x))
    cut = int(0.7 * len(x))
    fit, val = order[:cut], order[cut:]
    tree = train(x[fit], y[fit], seed=seed)
    prior = np.bincount(y[fit], minlength=PAIRS).astype(float)
    xt, yt = nlos(test_set)
    val_acc = top_k_accuracy(full_scores(tree, x[val], prior), np.arange(PAIRS), y[val], K_VALUES)
    test_acc = top_k_accuracy(full_scores(tree, xt, prior), np.arange(PAIRS), yt, K_VALUES)
    sizes = {"samples": int(len(train_set["los"])), "nlos_samples": int(len(x)), "fit": int(len(fit)),
             "validation": int(len(val)), "test_nlos": int(len(xt))}
    return tree, sizes, val_acc, test_acc


def write_report(report_dir: pathlib.Path, report: dict) -> str:
    """topk.json, topk.md and topk.png; the table as Markdown."""
    val_acc, test_acc = report["validation_topk"], report["test_topk"]
    report_dir.mkdir(parents=True, exist_ok=True)
    (report_dir / "topk.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = ["| K | validation acc. (%) | test acc. (%) |", "|---:|---:|---:|"]
    lines += [f"| {k} | {100 * val_acc[k]:.2f} | {100 * test_acc[k]:.2f} |" for k in K_VALUES]
    table = "\n".join(lines)
    (report_dir / "topk.md").write_text(
        f"Top-K accuracy of the decision tree (max depth {MAX_DEPTH}) on NLOS samples: {report['fit']} to fit, "
        f"{report['validation']} to validate (70/30 split), {report['test_nlos']} of a separate test flight."
        f"\n\n{table}\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogx(K_VALUES, [100 * val_acc[k] for k in K_VALUES], "o-", label="validation")
    ax.semilogx(K_VALUES, [100 * test_acc[k] for k in K_VALUES], "s-", label="test flight")
    ax.set(xlabel="K", ylabel="top-K accuracy (%)", title="Beam selection, decision tree")
    ax.grid(True)
    ax.legend()
    fig.tight_layout()
    fig.savefig(report_dir / "topk.png", dpi=100)
    plt.close(fig)
    return table


def main(argv=None) -> None:
    args = parse_args(argv)
    data = [load(r) for r in args.train]
    train_set = {k: np.concatenate([d[k] for d in data]) for k in data[0]}
    tree, sizes, val_acc, test_acc = fit_and_score(train_set, load(args.test), args.seed)
    save(tree, args.out)
    report = {"train_runs": args.train, "test_run": args.test, **sizes, "max_depth": MAX_DEPTH,
              "validation_topk": val_acc, "test_topk": test_acc}
    print(write_report(args.report_dir, report))
    print(f"model: {args.out}")


if __name__ == "__main__":
    main()
