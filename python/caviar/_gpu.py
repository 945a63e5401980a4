"""GPU use of this process, from NVIDIA's management library (nvidia-ml-py).

The core samples it after each stage for in-process modules; a NATS worker samples its
own process after each step. Where there is no NVIDIA driver or GPU, ``open_sampler``
returns None and the timings' GPU columns stay empty.
"""

from __future__ import annotations

import os


class GpuSampler:
    def __init__(self):
        import pynvml  # the nvidia-ml-py package

        pynvml.nvmlInit()
        self.nvml = pynvml
        self.handles = [pynvml.nvmlDeviceGetHandleByIndex(i) for i in range(pynvml.nvmlDeviceGetCount())]
        if not self.handles:
            raise RuntimeError("no NVIDIA GPU")
        self.pid = os.getpid()

    def _processes(self, h):
        n = self.nvml
        procs = list(n.nvmlDeviceGetComputeRunningProcesses(h))
        try:
            procs += list(n.nvmlDeviceGetGraphicsRunningProcesses(h))
        except n.NVMLError:
            pass
        return [p for p in procs if p.pid == self.pid]

    def sample(self) -> tuple[float, float] | None:
        """(utilisation %, GPU memory of this process in MiB). Utilisation is the
        device's (NVML has no cheap per-process figure), averaged over the devices this
        process uses, or over all devices while it uses none."""
        n = self.nvml
        try:
            mine = [(h, self._processes(h)) for h in self.handles]
            used = [h for h, p in mine if p]
            util = [n.nvmlDeviceGetUtilizationRates(h).gpu for h in (used or self.handles)]
            mem = sum((p.usedGpuMemory or 0) for _, ps in mine for p in ps) / 2**20
        except n.NVMLError:
            return None
        return float(sum(util) / len(util)), float(mem)


def open_sampler() -> GpuSampler | None:
    try:
        return GpuSampler()
    except Exception:  # no package, no driver, no GPU: nothing to measure
        return None
