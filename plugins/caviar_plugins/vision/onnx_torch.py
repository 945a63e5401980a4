"""An ONNX graph run by PyTorch, on torch's device: YOLO on the GPU wherever torch sees one.

onnxruntime's CPU provider ran the project's YOLO at 5.9 ms a frame on the lent H200, whose
onnxruntime has no CUDA provider while its torch has CUDA (issue #53). :class:`TorchGraph`
reads the ONNX file (the ``onnx`` package) and runs its nodes with torch operations, the same
arithmetic as onnxruntime in float32. It knows the operators of YOLOv8/YOLO11 detectors
(:data:`OPERATORS`); a file with another one is refused when loaded, naming the node.

* **Batches.** Ultralytics bakes the export's batch size (1) into the file, also into the
  head's ``Reshape`` shapes. Here the batch is the input's first dimension, whatever it is: a
  ``Reshape`` of a tensor led by the run's batch, whose target starts with the file's batch
  size, keeps the run's.
* **Shapes stay on the host.** Integer tensors (``Shape``, the arithmetic on it, integer
  constants) are computed on the CPU, float tensors on the device, so that a run needs nothing
  back from the device and never waits for it. The tests run the graph on torch's ``meta``
  device, which holds no values: any read of a device value would fail there.
* **CUDA graphs.** On CUDA a batch is padded to a power of two, and each such size's run is
  captured once as a CUDA graph (all in one memory pool) and then replayed: one launch instead
  of ~200 kernels launched from Python (``cuda_graphs``).
"""

from __future__ import annotations

import pathlib
import sys
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from caviar_plugins.torch_device import HOST, is_cuda, to_torch

OPERATORS = ("Add", "Concat", "Constant", "Conv", "Div", "Gather", "MaxPool", "Mul", "Reshape", "Resize",
             "Shape", "Sigmoid", "Slice", "Softmax", "Split", "Sub", "Transpose")
"""The ONNX operators :class:`TorchGraph` runs: those of Ultralytics' YOLOv8/YOLO11 detect exports."""


def _attributes(node) -> dict[str, Any]:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _symmetric_pads(pads: list[int], where: str) -> tuple[int, ...]:
    half = len(pads) // 2
    if list(pads[:half]) != list(pads[half:]):
        raise ValueError(f"{where}: asymmetric pads {pads} are not supported")
    return tuple(pads[:half])


class TorchGraph:
    """The ONNX model at ``path`` on torch ``device`` (a ``torch.device`` or its name):
    ``graph(batch)`` takes the input as a float32 numpy array or tensor and returns the first
    output on the device. ``input_shape``/``output_shape``: the file's (ints, or the names of
    dynamic dimensions); ``metadata``: its metadata (Ultralytics writes ``imgsz``, ``names``)."""

    def __init__(self, path, device: Any = HOST, cuda_graphs: bool | None = None):
        import torch

        try:
            import onnx
            from onnx import numpy_helper
        except ImportError:
            raise ValueError(f"{path}: running an ONNX model with torch needs the onnx package "
                             "(pip install 'caviar-plugins[onnx]')") from None
        self.path = pathlib.Path(path)
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such ONNX model file")
        try:
            model = onnx.load(str(self.path))
        except Exception as e:  # noqa: BLE001 - onnx raises its own (protobuf) errors
            raise ValueError(f"{self.path}: cannot load the ONNX model: {e}") from None
        self.device = torch.device(device)
        self.cuda_graphs = is_cuda(self.device) if cuda_graphs is None else bool(cuda_graphs)
        if self.cuda_graphs and not is_cuda(self.device):
            raise ValueError(f"{self.path}: cuda_graphs needs a CUDA device, not {self.device}")
        graph = model.graph
        shape = lambda v: [d.dim_value if d.HasField("dim_value") else d.dim_param  # noqa: E731
                           for d in v.type.tensor_type.shape.dim]
        weights = {i.name for i in graph.initializer}
        inputs = [i for i in graph.input if i.name not in weights]
        if len(inputs) != 1 or not graph.output:
            raise ValueError(f"{self.path}: expected one input and an output, got inputs "
                             f"{[i.name for i in inputs]} and outputs {[o.name for o in graph.output]}")
        self.input, self.output = inputs[0].name, graph.output[0].name
        self.input_shape, self.output_shape = shape(inputs[0]), shape(graph.output[0])
        self.metadata = {p.key: p.value for p in model.metadata_props}
        self.file_batch = self.input_shape[0] if isinstance(self.input_shape[0], int) else None
        self.arrays: dict[str, np.ndarray] = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
        self.arrays.update({n.output[0]: numpy_helper.to_array(n.attribute[0].t) for n in graph.node
                            if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value"})
        self.constants: dict[str, Any] = {name: self._tensor(a) for name, a in self.arrays.items()}
        self.steps: list[tuple[Callable, list[str], list[str]]] = []
        for k, node in enumerate(graph.node):
            where = f"{self.path}: node {k} ({node.op_type} {node.name!r})"
            if node.domain not in ("", "ai.onnx"):
                raise ValueError(f"{where}: the operator domain {node.domain!r} is not supported")
            if node.op_type == "Constant":
                if node.output[0] not in self.arrays:
                    raise ValueError(f"{where}: only Constant nodes holding a tensor ('value') are supported")
                continue
            if node.op_type not in OPERATORS:
                raise ValueError(f"{where}: the operator {node.op_type} is not one torch runs here "
                                 f"(known: {', '.join(OPERATORS)}); use runtime = \"onnxruntime\"")
            self.steps.append((self._operator(node, _attributes(node), where), list(node.input), list(node.output)))
        self._graphs = CudaGraphs(self._run, self.path.name) if self.cuda_graphs else None
        self._batch = self.file_batch

    def _tensor(self, array: np.ndarray):
        """A constant: floats on the device, integers (shapes, indices) on the host."""
        array = np.array(array)  # (a writable copy: onnx's arrays are read-only views of the file)
        return to_torch(array, self.device if np.issubdtype(array.dtype, np.floating) else HOST)

    def _operator(self, node, attrs: dict[str, Any], where: str) -> Callable:  # noqa: C901 - one table
        import torch
        import torch.nn.functional as F

        op = node.op_type

        def ints(t) -> list[int]:
            return [int(v) for v in t.reshape(-1).tolist()]  # (host tensors only: see _tensor)

        if op == "Conv":
            if attrs.get("auto_pad", b"NOTSET") not in (b"NOTSET", "NOTSET"):
                raise ValueError(f"{where}: auto_pad is not supported")
            kernel = attrs.get("kernel_shape")
            pads = _symmetric_pads(attrs.get("pads", [0] * (2 * len(kernel or [0, 0]))), where)
            stride, dilation, groups = attrs.get("strides", 1), attrs.get("dilations", 1), attrs.get("group", 1)
            return lambda x, w, b=None: F.conv2d(x, w, b, stride, pads, dilation, groups)
        if op == "MaxPool":
            if attrs.get("ceil_mode", 0) or attrs.get("storage_order", 0):
                raise ValueError(f"{where}: ceil_mode and storage_order are not supported")
            kernel = attrs["kernel_shape"]
            pads = _symmetric_pads(attrs.get("pads", [0] * (2 * len(kernel))), where)
            return lambda x: F.max_pool2d(x, kernel, attrs.get("strides", kernel), pads, attrs.get("dilations", 1))
        if op == "Resize":
            mode = attrs.get("mode", b"nearest")
            transform = attrs.get("coordinate_transformation_mode", b"half_pixel")
            if mode != b"nearest" or transform != b"asymmetric" or attrs.get("nearest_mode", b"round_prefer_floor") \
                    != b"floor":
                raise ValueError(f"{where}: only nearest, asymmetric, floor resizing is supported")

            scales_name = node.input[2] if len(node.input) > 2 else ""
            factors = None
            if scales_name:
                if scales_name not in self.arrays:
                    raise ValueError(f"{where}: the scales must be a constant of the file")
                factors = [float(v) for v in self.arrays[scales_name].reshape(-1)]
                if len(factors) != 4 or factors[:2] != [1.0, 1.0]:
                    raise ValueError(f"{where}: the scales {factors} must scale H and W only")

            def resize(x, roi=None, scales=None, sizes=None):
                if factors is None:  # (sizes: a host tensor)
                    return F.interpolate(x, size=ints(sizes)[2:], mode="nearest")
                return F.interpolate(x, scale_factor=factors[2:], mode="nearest")

            return resize
        if op == "Sigmoid":
            return lambda x: torch.sigmoid(x)
        if op in ("Add", "Sub", "Mul"):
            arithmetic: dict[str, Callable] = {"Add": torch.add, "Sub": torch.sub, "Mul": torch.mul}
            return arithmetic[op]
        if op == "Div":
            return lambda a, b: torch.div(a, b, rounding_mode=None if a.is_floating_point() else "trunc")
        if op == "Concat":
            return lambda *xs: torch.cat(xs, dim=attrs["axis"])
        if op == "Split":
            axis = attrs.get("axis", 0)

            def split(x, sizes=None):
                if sizes is None:
                    sizes = attrs.get("split") or [x.shape[axis] // len(node.output)] * len(node.output)
                    return torch.split(x, list(sizes), dim=axis)
                return torch.split(x, ints(sizes), dim=axis)

            return split
        if op == "Reshape":
            if attrs.get("allowzero", 0):
                raise ValueError(f"{where}: allowzero = 1 is not supported")

            def reshape(x, target):
                dims = ints(target)
                dims = [x.shape[i] if d == 0 else d for i, d in enumerate(dims)]
                if dims and self.file_batch is not None and dims[0] == self.file_batch and x.dim() > 1 \
                        and x.shape[0] == self._batch:
                    dims[0] = x.shape[0]  # (the batch the file baked in: the run's instead)
                return x.reshape(dims)

            return reshape
        if op == "Transpose":
            return lambda x: x.permute(*attrs["perm"]) if "perm" in attrs else x.permute(*reversed(range(x.dim())))
        if op == "Softmax":
            return lambda x: torch.softmax(x, dim=attrs.get("axis", -1))
        if op == "Shape":
            return lambda x: torch.tensor(list(x.shape), dtype=torch.int64)  # (on the host)
        if op == "Gather":
            return lambda x, i: torch.index_select(x, attrs.get("axis", 0), i.reshape(-1)).reshape(
                [*x.shape[:attrs.get("axis", 0)], *i.shape, *x.shape[attrs.get("axis", 0) + 1:]])
        if op == "Slice":
            def slice_(x, starts, ends, axes=None, steps=None):
                s, e = ints(starts), ints(ends)
                a = ints(axes) if axes is not None else list(range(len(s)))
                st = ints(steps) if steps is not None else [1] * len(s)
                index = [slice(None)] * x.dim()
                for ax, lo, hi, step in zip(a, s, e, st, strict=True):
                    if step <= 0:
                        raise ValueError(f"{where}: only positive steps are supported")
                    n = x.shape[ax]
                    index[ax] = slice(max(0, min(n, lo + n if lo < 0 else lo)),
                                      max(0, min(n, hi + n if hi < 0 else hi)), step)
                return x[tuple(index)]

            return slice_
        raise AssertionError(op)  # (OPERATORS lists every case above)

    def _run(self, x):
        self._batch = x.shape[0]
        values = dict(self.constants)
        values[self.input] = x
        for fn, ins, outs in self.steps:
            result = fn(*(values[n] if n else None for n in ins))
            if len(outs) == 1:
                values[outs[0]] = result
            else:
                values.update(zip(outs, result, strict=True))
        return values[self.output]

    def __call__(self, batch):
        """The first output for ``batch`` (N, ...), float32, on the device. One run at a time
        (the detector's threads share the model): on CUDA the CUDA graphs' buffers and
        cuDNN's float32 setting, a process-wide flag, are the run's while it lasts."""
        import torch

        with GPU_RUNS, float32_convolutions():
            x = to_torch(batch, self.device, torch.float32)
            n = x.shape[0]
            if self._graphs is not None and self._graphs.on:
                size = 1 << max(0, n - 1).bit_length()  # (a few graphs for any batch: padded to a power of two)
                if size != n:
                    x = torch.cat([x, x.new_zeros((size - n, *x.shape[1:]))])
                out = self._graphs(x)
                if out is not None:
                    return out[:n].clone()
            with torch.inference_mode():
                return self._run(x)[:n]


GPU_RUNS = threading.RLock()
"""Held by a run of a :class:`TorchGraph` or a CUDA-graph run of a
:class:`~caviar_plugins.vision.forest_torch.TorchForest`: one at a time in the process."""


class CudaGraphs:
    """``fn`` captured as CUDA graphs, one per input shape, all in one memory pool, then
    replayed. Call it holding :data:`GPU_RUNS`, and read its output before the next call (the
    buffer is the graph's). Where capture fails (a CUDA set-up that cannot), that is said once
    on stderr, calls return None from then on (``on`` is False) and the caller runs ``fn`` itself."""

    def __init__(self, fn: Callable, what: str):
        self.fn, self.what, self.on = fn, what, True
        self.graphs: dict[tuple, tuple[Any, Any, Any]] = {}
        self.pool: Any = None

    def __call__(self, x):
        key = tuple(x.shape)
        if key not in self.graphs:
            try:
                self.graphs[key] = capture(self.fn, x, self.pool)
            except RuntimeError as e:
                print(f"{self.what}: no CUDA graph ({e}); running kernel by kernel", file=sys.stderr)
                self.on = False
                return None
            self.pool = self.graphs[key][0].pool()
        graph, static_in, static_out = self.graphs[key]
        static_in.copy_(x)
        graph.replay()
        return static_out


def float32_convolutions():
    """A context in which cuDNN's convolutions compute in float32, not TF32 (PyTorch's default
    on Ampere and later GPUs): with TF32 the builtin YOLO's boxes on the H200 were up to 6 px
    from onnxruntime's on noise frames."""
    import torch

    return torch.backends.cudnn.flags(enabled=torch.backends.cudnn.enabled, benchmark=torch.backends.cudnn.benchmark,
                                      deterministic=torch.backends.cudnn.deterministic, allow_tf32=False)


def capture(fn: Callable, x, pool: Any = None) -> tuple[Any, Any, Any]:
    """A CUDA graph of ``fn(x)`` for ``x``'s shape, dtype and device: (graph, its input, its
    output). Warm-up runs on a side stream first, as PyTorch's documentation has it; then a
    run is ``input.copy_(new); graph.replay()`` and the output is read (or cloned) after.
    ``pool``: another graph's memory pool to share (safe here: one run at a time, its output
    copied out before the next)."""
    import torch

    static_in = x.clone()
    stream = torch.cuda.Stream(x.device)
    stream.wait_stream(torch.cuda.current_stream(x.device))
    with torch.inference_mode():
        with torch.cuda.stream(stream):
            for _ in range(2):
                fn(static_in)
        torch.cuda.current_stream(x.device).wait_stream(stream)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=pool, capture_error_mode="thread_local"):
            static_out = fn(static_in)
    return graph, static_in, static_out
