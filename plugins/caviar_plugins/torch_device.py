"""PyTorch's device, chosen in one place, and the one crossing between numpy and torch.

The radio network's link level (Sionna SYS, written in PyTorch) keeps its state and does its
work on one device: :func:`resolve` turns a ``device`` setting into it (``auto``: Sionna's
own choice, ``sionna.phy.config.device``, a GPU where there is one). numpy arrays enter
torch and leave it only through :func:`to_torch` and :func:`to_numpy`: a tensor made from
numpy elsewhere would sit on the CPU beside the others on the GPU, the mistake that stopped
the network at its first slot on an H100 (issue #39). ``tests/test_torch_device.py`` runs the
link level under :class:`DeviceGuard`, which fails any torch operation whose tensors are not
all on the chosen device and any numpy crossing outside these two functions.
"""

from __future__ import annotations

import functools
import inspect
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

_crossing = threading.local()


@functools.cache
def _blas_controller() -> Any:
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def one_blas_thread() -> Any:
    """A context in which numpy's BLAS (OpenBLAS) uses one thread. Between PyTorch's calls a
    multi-threaded product leaves BLAS threads spinning on the cores torch then needs: on the
    2-core development machine a Sionna SYS call ran 1.3x slower right after one (0.333 s
    against 0.255 s), and 1.0x with this around the product (which itself stays fast)."""
    return _blas_controller().limit(limits=1, user_api="blas")


HOST = "cpu"
"""The host's device, where numpy's arrays are: the default of the functions that take numpy
and compute in torch on a ``device`` (the link level's, where they run in the loop)."""


def resolve(setting: Any = "auto") -> Any:
    """The ``torch.device`` of a setting: ``auto`` (Sionna's, ``sionna.phy.config.device``),
    ``cpu``, ``cuda``, ``cuda:1``... (a ``torch.device`` is its own)."""
    import torch

    if isinstance(setting, torch.device):
        return setting
    if setting == "auto":
        import sionna.phy

        return torch.device(sionna.phy.config.device)
    try:
        return torch.device(setting)
    except RuntimeError as e:
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {setting!r} ({e})") from None


def check_setting(setting: str) -> str:
    """``setting`` if it names a device this machine has, else a ValueError naming ``device``:
    ``auto`` and ``cpu`` always, ``cuda`` and ``cuda:N`` where torch sees that CUDA GPU
    (torch is imported only for those)."""
    kind = setting.split(":", 1)[0]
    if kind not in ("auto", "cpu", "cuda") or (":" in setting and not setting.split(":", 1)[1].isdigit()):
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {setting!r}")
    if kind == "cuda":
        index = int(setting.split(":", 1)[1]) if ":" in setting else 0
        count = cuda_devices()
        if index >= count:
            has = "no CUDA GPU that torch can use" if count == 0 else f"{count} CUDA GPU(s), cuda:0 to cuda:{count - 1}"
            raise ValueError(f"device: {setting!r} names CUDA GPU {index}, and this machine has {has}; "
                             f"set device = 'auto' (a GPU where there is one) or 'cpu'")
    return setting


def cuda_devices() -> int:
    """The CUDA GPUs torch can use here (0 without a driver or a CUDA build of torch)."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


class _CrossingHere:
    """While entered, this thread is inside :func:`to_torch` or :func:`to_numpy` (a class, not a
    generator's context manager: a step makes dozens of crossings)."""

    def __enter__(self) -> None:
        _crossing.depth = getattr(_crossing, "depth", 0) + 1

    def __exit__(self, *exc: object) -> None:
        _crossing.depth -= 1


_crossing_here = _CrossingHere()


def crossing() -> bool:
    """Whether the current thread is inside :func:`to_torch` or :func:`to_numpy`."""
    return getattr(_crossing, "depth", 0) > 0


def compiled_once(module_name: str, name: str, function: Any) -> Any:
    """``torch.compile(function)``, made at the first call and kept as the attribute ``name`` of
    the module ``module_name`` (None until then): once a process, and what a bench wraps to time
    the compiled program apart (``benches/bench_host_overhead.py``)."""
    import sys

    module = sys.modules[module_name]
    if getattr(module, name) is None:
        import torch

        setattr(module, name, torch.compile(function))
    return getattr(module, name)


def to_torch(values: Any, device: Any, dtype: Any = None) -> Any:
    """A tensor of ``values`` (numpy, Python numbers, or a tensor, moved) on ``device``."""
    import torch

    with _crossing_here:
        if isinstance(values, torch.Tensor):
            return values.to(device=device, dtype=dtype)
        return torch.as_tensor(np.asarray(values), dtype=dtype, device=device)


def to_numpy(tensor: Any) -> np.ndarray:
    """A tensor's values as numpy (copied to the host from a GPU)."""
    with _crossing_here:
        return tensor.detach().cpu().numpy()


class DeviceGuard:
    """A ``torch.overrides.TorchFunctionMode`` that fails, naming the operation, when a torch
    operation's tensor operands are not all on ``device``, or a tensor is made from numpy
    (``torch.tensor``, ``torch.from_numpy``, ``torch.as_tensor``) or read into numpy
    (``Tensor.numpy``) outside :func:`to_torch` / :func:`to_numpy`. For tests, on any
    machine: a CPU-only one catches the crossings that would put a tensor on the wrong device
    of a GPU machine."""

    MAKERS = ("tensor", "from_numpy", "as_tensor")

    def __new__(cls, device: Any):
        import torch
        from torch.overrides import TorchFunctionMode

        class Guard(TorchFunctionMode):
            def __init__(self, device):
                super().__init__()
                self.device = torch.device(device)
                self.operations = 0

            def __torch_function__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                name = getattr(func, "__name__", str(func))
                if not crossing() and _called_from_this_project():
                    if func in (torch.tensor, torch.from_numpy, torch.as_tensor) and \
                            any(isinstance(a, np.ndarray) for a in args):
                        raise AssertionError(f"torch.{name} of a numpy array outside caviar_plugins.torch_device")
                    if name == "numpy":
                        raise AssertionError("Tensor.numpy() outside caviar_plugins.torch_device")
                found = [a.device for a in _tensors(args, kwargs) if isinstance(a, torch.Tensor)]
                if name not in ("to", "cpu", "cuda", "numpy") and any(d != self.device for d in found):
                    raise AssertionError(f"torch {name}: operands on {sorted({str(d) for d in found})}, "
                                         f"expected all on {self.device}")
                self.operations += 1
                return func(*args, **kwargs)

        return Guard(device)


def _called_from_this_project() -> bool:
    """Whether the torch call being checked was made by this project's code or a test (not
    by Sionna's or torch's own, which manage their devices themselves)."""
    frame: Any = inspect.currentframe()
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if not (module.startswith("torch") or module == __name__):
            return not module.startswith("sionna")
        frame = frame.f_back
    return False


def _tensors(args, kwargs) -> Iterator[Any]:
    for a in (*args, *kwargs.values()):
        if isinstance(a, (list, tuple)):
            yield from a
        else:
            yield a


def gpu_or_host() -> Any:
    """The first CUDA GPU torch sees, else the host: where models that are not Sionna's run
    (the detector's YOLO) when their ``device`` is ``auto``."""
    import torch

    return torch.device("cuda", 0) if torch.cuda.is_available() else torch.device(HOST)


def is_cuda(device: Any) -> bool:
    """Whether ``device`` (a ``torch.device`` or its name) is a CUDA GPU."""
    import torch

    return torch.device(device).type == "cuda"


def default_generator(device: Any) -> Any:
    """torch's default generator of ``device`` (what compiled code draws its random numbers from)."""
    import torch

    if is_cuda(device):
        index = torch.device(device).index
        return torch.cuda.default_generators[index if index is not None else torch.cuda.current_device()]
    return torch.default_generator
