"""YOLO through PyTorch (issue #53, part 2): the ONNX graph run by torch finds the same boxes as
onnxruntime, on whole batches, without reading a device value (so without waiting for a GPU);
``runtime``/``device`` choose it, and bad settings or files are named. On the GPU it runs as a
CUDA graph: ``scripts/gpu_check.py`` times it there."""

from __future__ import annotations

import numpy as np
import pytest

import caviar
from caviar_plugins.tools.training.twin_frames import write_dataset
from caviar_plugins.tools.training.yolo_eval import held_out_frames
from caviar_plugins.vision import yolo
from caviar_plugins.vision.onnx_torch import TorchGraph
from caviar_plugins.vision.yolo import BUILTIN_YOLO, YoloOnnx, choose_runtime
from configs import SAR_STAGES, episode, image_chain, module, route_past, waypoint_uav
from conftest import write_config

onnx = pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """24 held-out frames of the twin (persons, distractors, lost packets), 160 x 120."""
    out = tmp_path_factory.mktemp("frames")
    write_dataset(out, {"test": 24}, progress=False)
    return held_out_frames(out)[0]


def test_torch_runs_the_graph_as_onnxruntime_does_and_finds_the_same_boxes(images):
    ort = YoloOnnx(BUILTIN_YOLO, confidence=0.05)
    torch_ = YoloOnnx(BUILTIN_YOLO, confidence=0.05, runtime="torch", device="cpu")
    assert torch_.runtime == "torch" and torch_.session is None and torch_.size == ort.size == (128, 160)
    batch = np.stack([ort.letterbox(im)[0] for im in images]).transpose(0, 3, 1, 2).astype(np.float32) / 255
    a, b = ort.run(batch), torch_.run(batch)  # ONNX: 24 runs of the file's batch of 1; torch: one of 24
    assert a.shape == b.shape == (24, 5, 1680)
    # The raw outputs: boxes in input pixels (0-160), scores (sigmoid): float32 rounding apart.
    np.testing.assert_allclose(b[:, :4], a[:, :4], atol=2e-3)
    np.testing.assert_allclose(b[:, 4], a[:, 4], atol=2e-5)
    found_a, found_b = ort.detect_many(images), torch_.detect_many(images)
    boxes = 0
    for fa, fb in zip(found_a, found_b, strict=True):
        assert len(fa) == len(fb)  # (no score within 2e-5 of the threshold in these frames)
        for x, y in zip(fa, fb, strict=True):
            assert [y.x0, y.y0, y.x1, y.y1] == pytest.approx([x.x0, x.y0, x.x1, x.y1], abs=2e-3)
            assert y.score == pytest.approx(x.score, abs=2e-5)
        boxes += len(fa)
    assert boxes >= 10  # (persons were found: the comparison is not of empty lists)
    # One image alone gives what it gives in the batch (the batch the file baked in is not assumed).
    alone = [v for d in torch_.detect(images[3]) for v in (d.x0, d.y0, d.score)]
    assert len(alone) >= 3 and alone == pytest.approx([v for d in found_b[3] for v in (d.x0, d.y0, d.score)], abs=1e-4)


def test_the_graph_never_reads_a_device_value():
    """On torch's ``meta`` device tensors hold no values: any read of one (a shape computed on
    the device, a scale read back) fails. The run ends, with the output's shape for any batch:
    on a GPU it waits for nothing and can be captured as a CUDA graph."""
    graph = TorchGraph(BUILTIN_YOLO, device="meta", cuda_graphs=False)
    for n in (1, 7):
        out = graph(np.zeros((n, 3, 128, 160), np.float32))
        assert out.device.type == "meta" and tuple(out.shape) == (n, 5, 1680)
    assert graph.file_batch == 1 and graph.metadata["imgsz"] == "[128, 160]"
    with pytest.raises(ValueError, match="cuda_graphs needs a CUDA device"):
        TorchGraph(BUILTIN_YOLO, device="meta", cuda_graphs=True)


def tiny_model(path, op: str) -> None:
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 8, 8])
    y = helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 3, 8, 8])
    graph = helper.make_graph([helper.make_node(op, ["images"], ["out"], name="head")], "g", [x], [y])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def test_bad_files_and_settings_are_named(tmp_path):
    tiny_model(tmp_path / "tanh.onnx", "Tanh")
    with pytest.raises(ValueError, match=r"tanh.onnx: node 0 \(Tanh 'head'\): the operator Tanh is not one torch "
                                         r"runs here .* use runtime = \"onnxruntime\""):
        TorchGraph(tmp_path / "tanh.onnx")
    tiny_model(tmp_path / "sig.onnx", "Sigmoid")
    x = np.linspace(-4, 4, 192, dtype=np.float32).reshape(1, 3, 8, 8)
    np.testing.assert_allclose(TorchGraph(tmp_path / "sig.onnx")(x).numpy(), 1 / (1 + np.exp(-x)), rtol=1e-6)
    with pytest.raises(ValueError, match="nope.onnx: no such ONNX model file"):
        TorchGraph(tmp_path / "nope.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx: cannot load the ONNX model"):
        YoloOnnx(tmp_path / "junk.onnx", runtime="torch")
    with pytest.raises(ValueError, match="runtime = 'tensorrt': expected one of auto, onnxruntime, torch"):
        choose_runtime("tensorrt")


def test_auto_is_torch_where_torch_sees_a_gpu_and_onnxruntime_elsewhere(monkeypatch):
    monkeypatch.setattr(yolo, "torch_sees_gpu", lambda: False)
    assert choose_runtime("auto") == "onnxruntime"
    assert choose_runtime("auto", "cpu") == "torch"  # (a device named: torch on it)
    assert choose_runtime("onnxruntime", "cpu") == "onnxruntime"
    monkeypatch.setattr(yolo, "torch_sees_gpu", lambda: True)
    assert choose_runtime("auto") == "torch"


def detector(params: str) -> str:
    """One step of the YOLO detector alone, with ``params`` besides the model."""
    return episode(0.5, ["detection"], steps=2) + module("detector", "detection", "person-detector",
                                                         f'model = "yolo", {params}')


@pytest.mark.parametrize("params, expected", [
    ('runtime = "tensorrt"', "params.runtime = 'tensorrt': expected one of auto, onnxruntime, torch"),
    ('runtime = "torch", device = "gpu"', "params.device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'gpu'"),
    ('runtime = "torch", device = "cuda:0"', "params.device: 'cuda:0' names CUDA GPU 0, and this machine has no"),
])
def test_the_detectors_bad_runtime_settings_stop_the_run_naming_the_key(tmp_path, params, expected):
    import torch

    if "cuda:0" in params and torch.cuda.is_available():
        pytest.skip("this machine has the GPU the setting names")
    cfg = write_config(tmp_path, detector(params))
    with pytest.raises(caviar.RunError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run").run()


def test_the_forest_walked_by_torch_gives_scikit_learns_probabilities_bit_for_bit(images):
    """The main job's detector (the builtin pixel forest) on torch's device: the same float64
    probabilities as scikit-learn's own walk, so the same detections and the same recording."""
    from sklearn.ensemble import RandomForestClassifier

    from caviar_plugins.vision.forest_torch import TorchForest
    from caviar_plugins.vision.person_detector import PixelDetector, builtin_model, features

    cpu = builtin_model()
    x = np.concatenate([features(im) for im in images[:4]])
    on_torch = TorchForest(cpu.forest, "cpu")
    assert on_torch.trees == 40 and on_torch.depth >= 10
    expected = cpu.forest.predict_proba(x)[:, 1]
    got = on_torch(x)
    assert got.dtype == np.float64 and np.array_equal(got, expected)
    assert 0 < np.count_nonzero(got >= 0.5) < len(got)  # (persons and background both)
    device = PixelDetector(cpu.forest, cpu.min_pixels, cpu.threshold).to_device("cpu")
    found_cpu, found_torch = cpu.detect_many(images), device.detect_many(images)
    assert found_torch == found_cpu and sum(len(f) for f in found_cpu) >= 5
    # A forest of another shape (bootstrap off, 3 classes, ties at thresholds) too.
    rng = np.random.default_rng(3)
    xs = rng.integers(0, 4, (400, 5)).astype(np.float32)
    ys = (xs[:, 0] + xs[:, 1] > 3).astype(int) + (xs[:, 2] > 2)
    other = RandomForestClassifier(n_estimators=7, max_depth=6, bootstrap=False, random_state=0).fit(xs, ys)
    for column in range(3):
        assert np.array_equal(TorchForest(other, "cpu", column)(xs), other.predict_proba(xs)[:, column])
    with pytest.raises(ValueError, match=r"expected feature rows \(M, 5\), got \(4, 3\)"):
        TorchForest(other, "cpu")(np.zeros((4, 3)))
    # On CUDA a frame's rows are padded to a bucket (one CUDA graph each): the padding changes nothing.
    import torch

    assert [TorchForest.bucket(m) for m in (1, 1024, 1025, 19200)] == [1024, 1024, 2048, 32768]
    padded = np.zeros((5, TorchForest.bucket(len(xs))))
    padded[:, :len(xs)] = xs.T
    walk = TorchForest(other, "cpu", 2)._walk(torch.from_numpy(padded))
    assert np.array_equal(walk.numpy()[:len(xs)] / 7, other.predict_proba(xs)[:, 2])
    with pytest.raises(ValueError, match="cuda_graphs needs a CUDA device"):
        TorchForest(other, "cpu", cuda_graphs=True)


def loop(params: str) -> str:
    """8 steps of the SAR loop up to the detector (no mission), the detector with ``params``."""
    return episode(0.5, SAR_STAGES[:-1], steps=8, seed=2) + waypoint_uav() + image_chain(params, mission=False)


def test_the_loops_detections_are_the_same_with_the_forest_on_torch(tmp_path):
    """runtime = "torch" reaches the main job's detector (the builtin forest) and changes
    nothing it publishes: the loop's ai.detections are equal, message for message."""
    from caviar_plugins.vision.camera import default_targets

    tx, ty = default_targets()[1]
    route_past(tmp_path, (tx, ty))
    found = {}
    for name, params in (("cpu", 'runtime = "onnxruntime"'), ("torch", 'runtime = "torch", device = "cpu"')):
        cfg = write_config(tmp_path, loop(params), f"{name}.toml")
        log = caviar.Simulation.from_toml(cfg, out=tmp_path / name).run()
        assert log.status["status"] == "completed"
        found[name] = log.topic("ai.detections")["detections"].to_list()
    assert found["torch"] == found["cpu"] and sum(len(d) for d in found["cpu"]) >= 2


def test_auto_takes_torch_for_the_projects_models_only_and_refuses_by_name(tmp_path, monkeypatch):
    """On a machine with a GPU, ``auto`` moves the project's own models (YOLO, the builtin
    forest) to torch; a user's YOLO file stays on onnxruntime (its operators may be ones torch
    does not run here), a user's model that is no forest stays on scikit-learn, and asking
    ``torch`` for it names the key and the model."""
    import shutil
    import types

    from sklearn.ensemble import GradientBoostingClassifier

    from caviar_plugins.vision.pixel_detector import PixelDetector
    from caviar_plugins.vision.runtimes import detector_model

    monkeypatch.setattr(yolo, "torch_sees_gpu", lambda: True)  # (torch then runs on this CPU)
    shutil.copy(BUILTIN_YOLO, tmp_path / "mine.onnx")
    rng = np.random.default_rng(0)
    PixelDetector(GradientBoostingClassifier(n_estimators=3).fit(rng.random((40, 10)), np.arange(40) % 2)).save(
        tmp_path / "boost.pkl")

    def model(name, runtime="auto"):
        params = types.SimpleNamespace(model=name, runtime=runtime, device="auto", confidence=0.25, iou=0.45,
                                       person_class=0, workers=1)
        ctx = types.SimpleNamespace(params=params, resolve=lambda m: tmp_path / m)
        return detector_model(ctx, choose_runtime(runtime))

    assert model("yolo").model.runtime == "torch"
    assert model("mine.onnx").model.runtime == "onnxruntime"
    assert model("mine.onnx", "torch").model.runtime == "torch"
    assert model("builtin").on_device is not None
    assert model("boost.pkl").on_device is None
    with pytest.raises(ValueError, match=r"params.runtime = 'torch': boost.pkl: the pixel model is not a scikit-learn "
                                         r"forest of decision trees .*; it runs with scikit-learn"):
        model("boost.pkl", "torch")


def test_rows_with_nan_are_walked_by_scikit_learn():
    from caviar_plugins.vision.pixel_detector import PixelDetector, builtin_model

    cpu = builtin_model()
    device = PixelDetector(cpu.forest, cpu.min_pixels, cpu.threshold).to_device("cpu")
    x = np.random.default_rng(4).random((50, 10)).astype(np.float32)
    x[3, 2] = np.nan
    assert np.array_equal(device.person_probability(x), cpu.person_probability(x))
    with pytest.raises(ValueError, match="feature rows with NaN"):
        device.on_device(x)
