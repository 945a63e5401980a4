"""The third selector try of #26 (docs/paper-protocol.md, "A third try"): track the dominant
path's spatial frequency across the previous two beam sweeps, scored by leave-one-flight-out
top-1 on the six training flights. Pre-registered before any score; not adopted (it loses).

    bash scripts/sar-results.sh   # or only its six `caviar-core run ... paper-dataset-$i` lines
    .venv/bin/python scripts/paper_selector_tracking.py runs/paper-dataset-{0,1,2,3,4,5}

It reads only the training flights: the test flight is not loaded.

Model: the flat-DFT codebooks' gain for one plane wave is a product of Dirichlet kernels,
D8(α − c/64)·D8(β − c/8) on the 8 × 8 Tx array (codeword c) and D2(α' − r/4)·D2(β' − r/2) on
the 2 × 2 Rx array (codeword r). (α, β) is fitted on a 1/256 grid to the Tx sweep of the best
Rx beam, (α', β') to the Rx sweep of the best Tx beam; the prediction moves both by s times
their change over the previous step and picks the pair of largest predicted gain.
"""

from __future__ import annotations

import sys

import numpy as np

from caviar_plugins.beam_selection.knn import NearForestFarPrevious
from caviar_plugins.tools.baselines.paper_topk import hits, samples

GRID = np.arange(256) / 256
RADII_M = (0.25, 0.5, 1.0, 2.0)


def dirichlet(n: int, x: np.ndarray) -> np.ndarray:
    """|Σ_{m<n} exp(2πi·m·x)|² / n²."""
    return np.abs(np.exp(2j * np.pi * np.multiply.outer(x, np.arange(n))).sum(-1)) ** 2 / n**2


def side_patterns(n_row: int, n_col: int, n_code: int) -> tuple[np.ndarray, np.ndarray]:
    """Each codeword's gain factors for a plane wave exp(2πi(α·row + β·col)) on the array
    (flat index row + n_row·col, codeword exp(−2πi·k·c/n_code)): (grid, codewords) for α and β."""
    c = np.arange(n_code)
    return (dirichlet(n_row, GRID[:, None] - c[None, :] / n_code),
            dirichlet(n_col, GRID[:, None] - n_row * c[None, :] / n_code))


TX = side_patterns(8, 8, 64)
RX = side_patterns(2, 2, 4)


def fit(sweep: np.ndarray, side) -> np.ndarray:
    """(α, β) whose pattern correlates best with the sweep."""
    a, b = side
    m = a[:, None, :] * b[None, :, :]
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    score = m @ (sweep / (np.linalg.norm(sweep) + 1e-30))
    return np.array(np.unravel_index(np.argmax(score), score.shape)) / len(GRID)


def pattern(u: np.ndarray, side) -> np.ndarray:
    i, j = (int(round(x * len(GRID))) % len(GRID) for x in u)
    return side[0][i] * side[1][j]


def wrap(x):
    return (x + 0.5) % 1 - 0.5


_fits: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def fit_sweep(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    key = g.tobytes()
    if key not in _fits:
        g = g.reshape(4, 64)
        r, c = np.unravel_index(np.argmax(g), g.shape)
        _fits[key] = fit(g[r], TX), fit(g[:, c], RX)
    return _fits[key]


def track(s: dict[str, np.ndarray], mode: int, rx_too: bool) -> np.ndarray:
    """Predicted pairs: mode 0 (s = 0), 1 (s = 1), 2 (s = displacement ratio); the previous best
    pair where fewer than two previous sweeps exist."""
    out = np.argmax(s["previous_gains"], axis=1)
    for i in range(len(out)):
        g1, g2 = s["previous_gains"][i], s["previous2_gains"][i]
        if g1.max() <= 0 or g2.max() <= 0:
            continue
        (t1, r1), (t2, r2) = fit_sweep(g1), fit_sweep(g2)
        scale = float(mode)
        if mode == 2:
            p0, p1, p2 = s["position"][i], s["previous_position"][i], s["previous2_position"][i]
            d0, d1 = p0 - p1, p1 - p2
            scale = float(np.clip(d0 @ d1 / (d1 @ d1), 0, 3)) if d1 @ d1 > 1e-9 else 0.0
        tx = pattern(t1 + scale * wrap(t1 - t2), TX)
        if rx_too:
            pred = np.outer(pattern(r1 + scale * wrap(r1 - r2), RX), tx).ravel()
        else:
            pred = np.zeros(256)
            rb = int(np.argmax(g1)) // 64
            pred[rb * 64:(rb + 1) * 64] = tx
        out[i] = int(np.argmax(pred))
    return out


CANDIDATES = {"today: previous best pair": None, "T0 (s = 0)": (0, True), "T1 (s = 1)": (1, True),
              "T2 (s = displacement ratio)": (2, True), "T1, Tx only": (1, False), "T2, Tx only": (2, False)}


def main(runs: list[str]) -> None:
    parts = [samples(r) for r in runs]
    top1 = {c: {r: [] for r in RADII_M} for c in CANDIDATES}
    far = {c: {r: 0 for r in RADII_M} for c in CANDIDATES}
    alone = {c: [] for c in CANDIDATES}
    n_far = 0
    for i, held in enumerate(parts):
        rest = [p for j, p in enumerate(parts) if j != i]
        m = NearForestFarPrevious().fit(*(np.concatenate([p[k] for p in rest])
                                          for k in ("position", "previous_gains", "best_pair")))
        forest = m.forest_.predict(held["position"], held["previous_gains"])
        dist = m.distance_m(held["position"])
        has_prev = held["previous_gains"].max(axis=1) > 0
        best = np.argmax(held["gains"], axis=1)
        n_far += int((dist > 1.25).sum())
        for c, spec in CANDIDATES.items():
            rule = np.argmax(held["previous_gains"], axis=1) if spec is None else track(held, *spec)
            alone[c].append(hits(rule[has_prev], held["gains"][has_prev], (1,))[1])
            for r in RADII_M:
                pred = np.where((dist >= r) & has_prev, rule, forest)
                top1[c][r].append(hits(pred, held["gains"], (1,))[1])
                far[c][r] += int(((pred == best) & (dist > 1.25)).sum())
    print(f"| candidate (far side) | {' | '.join(f'r = {r:g} m' for r in RADII_M)} | the rule alone |")
    print(f"|---|{'---:|' * (len(RADII_M) + 1)}")
    for c in CANDIDATES:
        cells = " | ".join(f"{np.mean(top1[c][r]):.4f} ({far[c][r]}/{n_far})" for r in RADII_M)
        print(f"| {c} | {cells} | {np.mean(alone[c]):.4f} |")


if __name__ == "__main__":
    main(sys.argv[1:] or [f"runs/paper-dataset-{i}" for i in range(6)])
