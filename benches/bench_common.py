"""Helpers the speed benchmarks share: the machine a number was measured on, timing two
variants in turn, and the accuracy summary of links against a reference."""

from __future__ import annotations

import statistics
import time

import numpy as np

from caviar_plugins.rt import configure_drjit

configure_drjit()


def machine() -> str:
    """The machine this run measured on, as it is (CPU, GPU, Dr.Jit variant, torch device):
    :func:`caviar_plugins.machine.summary`. (A development machine: nothing else heavy ran.)"""
    from caviar_plugins.machine import summary

    return summary()


def interleaved(old, new, reps: int) -> tuple[float, float]:
    a, b = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        old()
        t1 = time.perf_counter()
        new()
        b.append(time.perf_counter() - t1)
        a.append(t1 - t0)
    return statistics.median(a), statistics.median(b)



def accuracy_summary(errors: dict[str, list], same: dict[str, list]) -> dict:
    """Per label (old, new, other_seed): the path-gain error's median and max (dB) against the
    reference, and the share of links whose best pair is the reference's (%)."""
    accuracy: dict = {f"{label}_path_gain_error_db_{stat}": float(f(errors[label]))
                      for label in errors for stat, f in (("median", np.median), ("max", np.max))}
    accuracy.update({f"{label}_same_best_pair_pct": 100 * float(np.mean(same[label])) for label in errors})
    return accuracy

