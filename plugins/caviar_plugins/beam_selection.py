"""Beam selection from the UAV position: a scikit-learn decision tree (the paper's,
max depth 15), or the random and oracle baselines.

* ``tree``: predicts the beam pair (0 … 255) from (x, y, z) with a tree trained by
  ``python -m caviar_plugins.beam_selection train`` (see :func:`train`).
* ``random``: a uniformly drawn pair (Rx 0–3 × Tx 0–63), seeded.
* ``oracle``: publishes nothing, so the communications module uses the best pair.

Choices go to ``ai.beam.selection`` as ``{"UE_Id": …, "beam_pair": i}``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import pickle

import numpy as np

import caviar

SELECTION = "ai.beam.selection"
METHODS = ("tree", "random", "oracle")


class BeamSelector(caviar.Plugin):
    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params:
        method: str = "tree"
        model: str = ""
        """Pickled tree from ``train`` (relative to the config file); needed for ``tree``."""
        pairs: int = 256

        def __post_init__(self):
            if self.method not in METHODS:
                raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
            if self.method == "tree" and not self.model:
                raise ValueError("method 'tree' needs `model`, a tree trained by "
                                 "`python -m caviar_plugins.beam_selection train`")

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.tree = None
        if p.method == "tree":
            self.tree = pickle.loads(ctx.resolve(p.model).read_bytes())

    def step(self, t, inbox):
        p = self.ctx.params
        if p.method == "oracle":
            return
        for m in inbox.on("3D.mobility.positions"):
            pos = m.data["position"]
            if p.method == "random":
                pair = int(self.ctx.rng.integers(p.pairs))
            else:
                pair = int(self.tree.predict(np.array([[pos["x"], pos["y"], pos["z"]]]))[0])
            yield SELECTION, {"UE_Id": m.data["UE_Id"], "beam_pair": pair}


def top_k_accuracy(scores: np.ndarray, classes: np.ndarray, truth: np.ndarray, ks) -> dict[int, float]:
    """Share of samples whose true pair is among the k highest-scoring pairs."""
    order = classes[np.argsort(-scores, axis=1)]
    return {k: float(np.mean([t in row[:k] for t, row in zip(truth, order)])) for k in ks}


def train(positions: np.ndarray, best: np.ndarray, seed: int = 0, max_depth: int = 15):
    from sklearn.tree import DecisionTreeClassifier

    tree = DecisionTreeClassifier(max_depth=max_depth, random_state=seed)
    tree.fit(positions, best)
    return tree


def save(tree, path: pathlib.Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(tree))


K_VALUES = (1, 2, 3, 4, 5, 10, 25, 50, 75, 100)


def full_scores(tree, positions: np.ndarray, prior: np.ndarray, pairs: int = 256) -> np.ndarray:
    """Scores of all pairs: the tree's class probabilities; pairs it never predicts are
    ranked after them by how often they were best in training (``prior``)."""
    scores = np.zeros((len(positions), pairs))
    scores[:, tree.classes_] = tree.predict_proba(positions)
    return scores + 1e-9 * prior / max(prior.max(), 1)


def main() -> None:
    import argparse
    import json

    from caviar_plugins.beam_dataset import load

    ap = argparse.ArgumentParser(description="Fit the beam-selection tree on NLOS samples and write the top-K table.")
    ap.add_argument("command", choices=["train"])
    ap.add_argument("--train", nargs="+", required=True, help="run directories of the dataset blueprint")
    ap.add_argument("--test", required=True, help="run directory of a separate test flight")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("models/beam-tree.pkl"))
    ap.add_argument("--report-dir", type=pathlib.Path, default=pathlib.Path("docs/results"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    data = [load(r) for r in args.train]
    train_set = {k: np.concatenate([d[k] for d in data]) for k in data[0]}
    test_set = load(args.test)
    nlos = ~train_set["los"].astype(bool)
    x, y = train_set["position"][nlos], train_set["best_pair"][nlos]
    rng = np.random.default_rng(args.seed)
    order = rng.permutation(len(x))
    cut = int(0.7 * len(x))
    fit, val = order[:cut], order[cut:]
    tree = train(x[fit], y[fit], seed=args.seed)
    prior = np.bincount(y[fit], minlength=256).astype(float)
    t_nlos = ~test_set["los"].astype(bool)
    xt, yt = test_set["position"][t_nlos], test_set["best_pair"][t_nlos]
    val_acc = top_k_accuracy(full_scores(tree, x[val], prior), np.arange(256), y[val], K_VALUES)
    test_acc = top_k_accuracy(full_scores(tree, xt, prior), np.arange(256), yt, K_VALUES)
    save(tree, args.out)

    report = {"train_runs": args.train, "test_run": args.test, "samples": int(len(train_set["los"])),
              "nlos_samples": int(nlos.sum()), "fit": int(len(fit)), "validation": int(len(val)),
              "test_nlos": int(len(xt)), "max_depth": 15, "validation_topk": val_acc, "test_topk": test_acc}
    args.report_dir.mkdir(parents=True, exist_ok=True)
    (args.report_dir / "topk.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = ["| K | validation acc. (%) | test acc. (%) |", "|---:|---:|---:|"]
    lines += [f"| {k} | {100 * val_acc[k]:.2f} | {100 * test_acc[k]:.2f} |" for k in K_VALUES]
    table = "\n".join(lines)
    (args.report_dir / "topk.md").write_text(
        f"Top-K accuracy of the decision tree (max depth 15) on NLOS samples: {len(fit)} to fit, "
        f"{len(val)} to validate (70/30 split), {len(xt)} of a separate test flight.\n\n{table}\n")
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
    fig.savefig(args.report_dir / "topk.png", dpi=100)
    print(table)
    print(f"model: {args.out}")


if __name__ == "__main__":
    main()
