"""Dr.Jit set-up: where its LLVM backend finds libLLVM, how many CPU threads it uses, and
the untyped handles and aligned arrays the ray-tracing code builds its arrays with.

Sionna RT 2.x runs on Dr.Jit. Without a GPU it uses the LLVM backend, which needs
libLLVM >= 16 (Debian: ``libllvm19``); :func:`configure_drjit` points Dr.Jit at it and must
run before Sionna RT, Mitsuba or Dr.Jit are imported. Nothing here names a backend: array
types come from the active Mitsuba variant (``mi.Float``, ``mi.UInt``...), which Sionna RT
chooses (CUDA where a GPU is found, LLVM otherwise).
"""

from __future__ import annotations

import glob
import os
from typing import Any

import numpy as np


def configure_drjit() -> None:
    """Sets DRJIT_LIBLLVM_PATH to the newest libLLVM >= 16 found, unless already set.
    Must run before sionna/mitsuba/drjit are imported."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    candidates = []
    for path in glob.glob("/usr/lib/*-linux-gnu/libLLVM.so.*") + glob.glob("/usr/lib/*-linux-gnu/libLLVM-*.so"):
        digits = "".join(ch if ch.isdigit() else " " for ch in os.path.basename(path)).split()
        if digits and int(digits[0]) >= 16:
            candidates.append((int(digits[0]), path))
    if candidates:
        os.environ["DRJIT_LIBLLVM_PATH"] = max(candidates)[1]


RGB_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
"""Mitsuba variants :func:`mitsuba` tries, in order, when Sionna RT is not installed to
choose one (the GPU where there is one)."""


def mitsuba() -> Any:
    """Mitsuba with a variant set: Sionna RT's if it is installed (it chooses its variant,
    CUDA where a GPU is found, on import, and only if none is set), else the first of
    :data:`RGB_VARIANTS` this machine runs. Array types then come from it (``mi.Float``,
    ``mi.Float64``...), never from a backend named here."""
    configure_drjit()
    import mitsuba as mi

    if mi.variant() is None:
        try:
            import sionna.rt  # noqa: F401
        except ImportError:
            for variant in RGB_VARIANTS:
                try:
                    mi.set_variant(variant)
                    break
                except (ImportError, AttributeError, RuntimeError):
                    continue
    return mi


def set_thread_count(threads: int) -> None:
    """Dr.Jit's CPU threads (``threads`` > 0; 0 leaves Dr.Jit's default, all cores). On the
    CPU the solver's parallel sums differ in the last float bits from run to run; one thread
    makes runs bit-identical."""
    if threads < 0:
        raise ValueError(f"threads: expected 0 (all cores) or more, got {threads}")
    if threads > 0:
        configure_drjit()
        import drjit as dr

        dr.set_thread_count(threads)


def jit() -> tuple[Any, Any]:
    """Dr.Jit and Mitsuba, untyped: Dr.Jit's stubs do not know Mitsuba's array types."""
    configure_drjit()
    import drjit
    import mitsuba

    return drjit, mitsuba


def aligned_array(cls, values: np.ndarray):
    """A Dr.Jit array of ``values``, made from 64-byte aligned memory: Dr.Jit takes numpy's
    memory as it is and compiles a kernel anew for each alignment it meets."""
    values = np.ascontiguousarray(values)
    buf = np.empty(values.nbytes + 64, dtype=np.uint8)
    start = -buf.ctypes.data % 64
    aligned = buf[start:start + values.nbytes].view(values.dtype)
    aligned[...] = values.ravel()
    return cls(aligned)
