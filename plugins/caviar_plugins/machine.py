"""The machine a figure was measured on, as it is: CPU, GPU, Dr.Jit's variant and torch's device.

Benchmarks and ``scripts/gpu_check.py`` write :func:`describe` beside every number, so that a
figure names the machine that gave it (on the lent H200 every network row once said "no GPU
... Dr.Jit LLVM", hard-coded). Each part is read where it is: the CPU from ``/proc/cpuinfo``,
the GPU from NVIDIA's management library (nvidia-ml-py) or else from torch, the Dr.Jit variant
from Mitsuba as Sionna RT chose it (CUDA where a GPU is found, LLVM otherwise), torch's device
from Sionna SYS's choice (:func:`caviar_plugins.torch_device.resolve`). A part that cannot be
read says why instead of guessing.
"""

from __future__ import annotations

import os
import platform
from typing import Any


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def gpu_name() -> str | None:
    """The first GPU's name and memory ("NVIDIA H200, 140 GiB"), None where there is none."""
    try:
        import pynvml  # the nvidia-ml-py package

        pynvml.nvmlInit()
        handle = pynvml.nvmlDeviceGetHandleByIndex(0)
        name = pynvml.nvmlDeviceGetName(handle)
        memory = pynvml.nvmlDeviceGetMemoryInfo(handle).total / 2**30
        return f"{name if isinstance(name, str) else name.decode()}, {memory:.0f} GiB"
    except Exception:  # noqa: BLE001 - no package, no driver, no GPU: ask torch instead
        pass
    try:
        import torch

        if torch.cuda.is_available():
            props = torch.cuda.get_device_properties(0)
            return f"{props.name}, {props.total_memory / 2**30:.0f} GiB"
    except Exception:  # noqa: BLE001 - no torch, or a broken CUDA set-up: no GPU to name
        pass
    return None


def drjit_variant() -> str:
    """The Mitsuba variant ray tracing runs on (``cuda_ad_mono_polarized``, ``llvm_ad_...``)."""
    try:
        from caviar_plugins.rt.drjit_setup import mitsuba

        return str(mitsuba().variant())
    except Exception as e:  # noqa: BLE001 - not installed or no backend: say so
        return f"unavailable ({type(e).__name__}: {e})"


def torch_device() -> str:
    """The device the radio network's link level runs on by default (Sionna SYS's choice)."""
    try:
        from caviar_plugins.torch_device import resolve

        return str(resolve("auto"))
    except Exception:  # noqa: BLE001 - no Sionna SYS: torch's own view
        pass
    try:
        from caviar_plugins.torch_device import gpu_or_host

        return str(gpu_or_host())
    except ImportError:
        return "unavailable (torch is not installed)"


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for package in ("drjit", "mitsuba", "sionna-rt", "sionna-no-rt", "torch", "onnxruntime"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            pass
    return out


def describe() -> dict[str, Any]:
    """Everything above, and ``name``: the GPU where there is one, else the CPU and its cores."""
    out: dict[str, Any] = {"processor": cpu_name(), "cores": os.cpu_count(), "gpu": gpu_name(),
                           "platform": platform.platform(), "drjit_variant": drjit_variant(),
                           "torch_device": torch_device(), **versions()}
    out["name"] = out["gpu"] or f"no GPU ({out['processor']}, {out['cores']} cores)"
    return out


def summary(d: dict[str, Any] | None = None) -> str:
    """One line of :func:`describe` for a result file."""
    d = describe() if d is None else d
    gpu = f"GPU {d['gpu']}" if d["gpu"] else "no GPU"
    return (f"{d['processor']}, {d['cores']} cores, {gpu}; Dr.Jit variant {d['drjit_variant']}, torch device "
            f"{d['torch_device']}; {d['platform']}; sionna-rt {d.get('sionna-rt', '?')}, torch {d.get('torch', '?')}")
