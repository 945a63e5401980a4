"""LiDAR-aided beam selection, as in the Raymobtime LiDAR papers (Klautau et al., "LIDAR
Data for Deep Learning-Based mmWave Beam-Selection", IEEE WCL 2019): a small CNN on the
occupancy grid around the UE, with and without its position, against position-only
selection (:class:`~caviar_plugins.beam_selection.knn.GainKNN`, the project's best) on the
same flights.

    python -m caviar_plugins.tools.baselines.lidar_selector --train RUN [RUN ...] --test RUN \\
        [--out docs/results/beam-lidar.json] [--epochs 40] [--seed 0]

The runs are ``beam-dataset`` runs with a ``lidar`` module (``blueprints/beam-lidar``). Each
record's grid is :func:`~caviar_plugins.tools.export.raymobtime.occupancy_grid`'s (40 × 40
× 20 cells of 1 m): its 20 height slices are the CNN's channels, with one more channel for
the base station's marker (the direction toward it). Targets are Raymobtime's: the pairs
within 6 dB of the best, their gains normalised to sum 1 (``beams_log_scale``), trained
with cross-entropy. Scores on the test flight: top-1 and top-10 accuracy (the best pair
among the k highest scores) and the throughput of the chosen pair, and of the best of the
top 10 after sweeping them, as a share of the oracle's (the link budget of ``sionna-link``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
from typing import Any

import numpy as np

GRID = (40, 40, 20)
CELL_M = 1.0
THRESHOLD_DB = 6.0
KS = (1, 2, 3, 5, 10, 20)


def features(run: pathlib.Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(grids (N, 21, 40, 40) float32, positions (N, 3), gains (N, pairs)) of a run's records
    that have a LiDAR sweep."""
    from caviar.rundir import RunDir
    from caviar_plugins.beam_selection.dataset import load_multimodal
    from caviar_plugins.tools.export.raymobtime import BASE_STATION, OBSTACLE, occupancy_grid, transmitter_of

    arrays, sweeps, _, _ = load_multimodal(run)
    tx = transmitter_of(RunDir(run).config_text())
    if tx is None:
        raise ValueError(f"{run}: no link module to take the transmitter from")
    keep = [k for k, s in enumerate(sweeps) if s is not None]
    if not keep:
        raise ValueError(f"{run}: no record has a LiDAR sweep (a run with a lidar module)")
    grids = []
    for k in keep:
        g = occupancy_grid(sweeps[k], arrays["position"][k], GRID, CELL_M, np.asarray(tx))  # type: ignore[arg-type]
        slices = (g == OBSTACLE).transpose(2, 0, 1).astype(np.float32)  # (Z, X, Y)
        marker = (g == BASE_STATION).any(axis=2).astype(np.float32)[None]
        grids.append(np.concatenate([slices, marker]))
    gains = arrays["gains"].reshape(len(arrays["gains"]), -1)[keep].astype(np.float64)
    return np.stack(grids), arrays["position"][keep].astype(np.float64), gains


def soft_targets(gains: np.ndarray, threshold_db: float = THRESHOLD_DB) -> np.ndarray:
    """Raymobtime's ``beams_log_scale``: the pairs within ``threshold_db`` of each sample's
    best keep their gain, the others 0, normalised to sum 1."""
    g = np.asarray(gains, dtype=np.float64)
    db = 10 * np.log10(np.maximum(g, 1e-30))
    kept = np.where(db >= db.max(axis=1, keepdims=True) - threshold_db, g, 0.0)
    return kept / np.maximum(kept.sum(axis=1, keepdims=True), 1e-30)  # (no path at all: zeros)


def top_k(scores: np.ndarray, gains: np.ndarray, ks=KS) -> dict[str, float]:
    """Share of samples whose best pair is among the k highest scores."""
    best = gains.argmax(axis=1)
    order = np.argsort(-scores, axis=1, kind="stable")
    return {f"top{k}": float(np.mean([b in o[:k] for b, o in zip(best, order, strict=True)])) for k in ks}


def throughput_ratio(scores: np.ndarray, gains: np.ndarray, sweep: int = 1) -> float:
    """Mean throughput of the best of the ``sweep`` highest-scored pairs over the oracle's."""
    from caviar_plugins.radio.link_budget import LinkBudget

    budget = LinkBudget()
    order = np.argsort(-scores, axis=1, kind="stable")[:, :sweep]
    chosen = np.take_along_axis(gains, order, axis=1).max(axis=1)
    return float(budget.throughput_mbps(chosen).mean() / budget.throughput_mbps(gains.max(axis=1)).mean())


def _model(channels: int, pairs: int, with_position: bool) -> Any:
    import torch
    from torch import nn

    class BeamCNN(nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = nn.Sequential(
                nn.Conv2d(channels, 16, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
                nn.Conv2d(16, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
                nn.Conv2d(32, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
                nn.Flatten(), nn.Dropout(0.3))
            flat = 32 * (GRID[0] // 8) * (GRID[1] // 8)
            self.head = nn.Sequential(nn.Linear(flat + (3 if with_position else 0), 128), nn.ReLU(),
                                      nn.Linear(128, pairs))

        def forward(self, grid, position):
            z = self.conv(grid)
            if with_position:
                z = torch.cat([z, position], dim=1)
            return self.head(z)

    return BeamCNN()


def train_cnn(grids: np.ndarray, positions: np.ndarray, targets: np.ndarray, with_position: bool,
              epochs: int, seed: int, device: Any) -> tuple[Any, np.ndarray, np.ndarray]:
    """The trained CNN and the position normalisation (mean, std)."""
    import torch

    from caviar_plugins.torch_device import to_torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean, std = positions.mean(axis=0), positions.std(axis=0)
    std = np.where(std < 1e-6, 1.0, std)  # (a coordinate constant in training: left unscaled)
    model = _model(grids.shape[1], targets.shape[1], with_position).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-4)
    g = to_torch(grids, device, torch.float32)
    p = to_torch((positions - mean) / std, device, torch.float32)
    y = to_torch(targets, device, torch.float32)
    model.train()
    for _ in range(epochs):
        for batch in np.array_split(rng.permutation(len(g)), max(1, len(g) // 32)):
            idx = to_torch(batch, device, torch.long)
            logits = model(g[idx], p[idx])
            loss = -(y[idx] * torch.log_softmax(logits, dim=1)).sum(dim=1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    model.eval()
    return model, mean, std


def predict(model: Any, grids: np.ndarray, positions: np.ndarray, mean: np.ndarray, std: np.ndarray,
            device: Any) -> np.ndarray:
    import torch

    from caviar_plugins.torch_device import to_numpy, to_torch

    with torch.no_grad():
        logits = model(to_torch(grids, device, torch.float32),
                       to_torch((positions - mean) / std, device, torch.float32))
    return to_numpy(logits)


def compare(train_runs: list[pathlib.Path], test_run: pathlib.Path, epochs: int = 40, seed: int = 0,
            device_setting: str = "auto") -> dict[str, Any]:
    from caviar_plugins.beam_selection.knn import GainKNN
    from caviar_plugins.torch_device import resolve

    device = resolve(device_setting)
    parts = [features(r) for r in train_runs]
    g_tr, p_tr, y_tr = (np.concatenate([part[i] for part in parts]) for i in range(3))
    g_te, p_te, y_te = features(test_run)
    targets = soft_targets(y_tr)
    scores: dict[str, np.ndarray] = {}
    wall: dict[str, float] = {}
    t0 = time.perf_counter()
    knn = GainKNN(k=5).fit(p_tr, y_tr)
    scores["position (k-NN)"] = knn.scores(p_te)
    wall["position (k-NN)"] = time.perf_counter() - t0
    for name, with_position in (("LiDAR (CNN)", False), ("LiDAR + position (CNN)", True)):
        t0 = time.perf_counter()
        model, mean, std = train_cnn(g_tr, p_tr, targets, with_position, epochs, seed, device)
        scores[name] = predict(model, g_te, p_te, mean, std, device)
        wall[name] = time.perf_counter() - t0
    result: dict[str, Any] = {"train_runs": [str(r) for r in train_runs], "test_run": str(test_run),
                              "train_samples": int(len(g_tr)), "test_samples": int(len(g_te)),
                              "pairs": int(y_tr.shape[1]), "grid": list(GRID), "cell_m": CELL_M,
                              "epochs": epochs, "seed": seed, "device": str(device), "selectors": {}}
    for name, s in scores.items():
        result["selectors"][name] = {**top_k(s, y_te), "throughput_of_oracle": round(throughput_ratio(s, y_te), 4),
                                     "throughput_of_oracle_top10_swept": round(throughput_ratio(s, y_te, 10), 4),
                                     "train_s": round(wall[name], 2)}
    return result


def draw(result: dict[str, Any], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in result["selectors"].items():
        ax.plot(KS, [100 * r[f"top{k}"] for k in KS], "o-", label=f"{name}: {100 * r['throughput_of_oracle']:.0f} % "
                f"of the oracle's throughput")
    ax.set(xlabel="k (pairs swept)", ylabel="top-k accuracy (%)", xscale="log", ylim=(0, 100),
           title=f"Beam selection, {result['test_samples']} test samples off the paper's street")
    ax.set_xticks(KS, [str(k) for k in KS])
    ax.grid(True, alpha=0.4)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.baselines.lidar_selector",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", type=pathlib.Path, nargs="+", required=True)
    ap.add_argument("--test", type=pathlib.Path, required=True)
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/beam-lidar.json"))
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="auto", help="the torch device (auto: Sionna's)")
    args = ap.parse_args(argv)
    result = compare(args.train, args.test, args.epochs, args.seed, args.device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    draw(result, args.out.with_suffix(".png"))
    for name, r in result["selectors"].items():
        swept = 100 * r["throughput_of_oracle_top10_swept"]
        print(f"{name}: top-1 {100 * r['top1']:.1f} %, top-10 {100 * r['top10']:.1f} %, throughput "
              f"{100 * r['throughput_of_oracle']:.1f} % of the oracle's ({swept:.1f} % sweeping the top 10)")
    return result


if __name__ == "__main__":
    main()
