"""YOLO trained on the twin's own frames, in the loop through ONNX (issue #27).

The labels are checked against the camera's geometry, AP against a hand computation, the
ONNX layouts with hand-built models, the builtin model on held-out frames it never saw, and
the SAR loop with it; a tiny training run goes through Ultralytics and the export."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

import caviar
from caviar_plugins.tools.training.twin_frames import FrameConfig, TwinFrames, write_dataset, yolo_boxes
from caviar_plugins.tools.training.yolo_eval import evaluate, held_out_frames, pixel_detect, yolo_detect
from caviar_plugins.vision import person_detector as detector
from caviar_plugins.vision.yolo import BUILTIN_YOLO, YoloOnnx, average_precision, iou, nms
from configs import SAR_STAGES, episode, image_chain, route_past, the_rescue, waypoint_uav
from conftest import write_config


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """40 held-out test frames (the test split's own scene and flights)."""
    out = tmp_path_factory.mktemp("frames")
    meta = write_dataset(out, {"test": 40}, progress=False)
    return out, meta


def project(point, camera, heading_deg: float, cfg: FrameConfig) -> tuple[float, float]:
    """(row, col) of a point seen by a nadir pinhole camera whose image-up is the heading:
    written out independently of Mitsuba."""
    h = math.radians(heading_deg)
    up, right = np.array([math.cos(h), math.sin(h)]), np.array([math.sin(h), -math.cos(h)])
    d = np.asarray(point[:2], dtype=float) - camera[:2]
    depth = camera[2] - point[2]
    metres_per_px = 2 * depth * math.tan(math.radians(cfg.fov_deg) / 2) / cfg.width
    return cfg.height / 2 - d @ up / metres_per_px, cfg.width / 2 + d @ right / metres_per_px


def test_a_persons_box_is_where_the_camera_geometry_puts_it():
    cfg = FrameConfig(persons_per_100m=20.0, distractors_per_100m=0.0, empty_share=0.0)
    twin = TwinFrames(cfg, seed=11, flights=2)
    light = {"sun": np.array([0.0, 0.0, 1.0]), "sun_colour": np.ones(3), "sky": 0.3, "exposure": 1.0}
    checked = 0
    for person in twin.persons[:6]:
        for heading in (0.0, 90.0, 200.0):
            camera = np.array([person.x + 1.0, person.y - 0.5, person.z + 10.0])
            _, labels = twin.render(camera, heading, light)
            boxes = {p: b for p, *b in yolo_boxes(labels, cfg.supersample)}
            assert person.index in boxes, (person, heading)
            x0, y0, x1, y1 = boxes[person.index]
            row, col = project((person.x, person.y, person.z), camera, heading, cfg)
            # The person's reference point (its centre on the ground) is inside its box, and
            # the box is person-sized: 0.3-2.2 m along its longer side at this altitude.
            assert x0 - 1 <= col <= x1 + 1 and y0 - 1 <= row <= y1 + 1, (person, heading, (row, col), boxes)
            metres_per_px = 2 * 10.0 * math.tan(math.radians(cfg.fov_deg) / 2) / cfg.width
            assert 0.3 <= max(x1 - x0, y1 - y0) * metres_per_px <= 2.2, (person, (x0, y0, x1, y1))
            checked += 1
    assert checked == 18


def test_the_dataset_is_ultralytics_shaped_and_labelled(frames):
    out, meta = frames
    assert (out / "data.yaml").read_text().splitlines()[1:4] == ["train: images/train", "val: images/val",
                                                                  "test: images/test"]
    split = meta["splits"]["test"]
    assert split["frames"] == 40 and split["boxes"] > 20 and split["frames_without_person"] >= 1
    assert sum(split["boxes_by_pose"].values()) == split["boxes"] and min(split["boxes_by_pose"].values()) >= 1
    assert meta["render_s_per_frame"] > 0
    lines = [ln for p in (out / "labels" / "test").glob("*.txt") for ln in p.read_text().splitlines()]
    assert len(lines) == split["boxes"]
    values = np.array([[float(v) for v in ln.split()] for ln in lines])
    assert np.all(values[:, 0] == 0) and np.all((values[:, 1:] > 0) & (values[:, 1:] <= 1))


def test_average_precision_as_computed_by_hand():
    truths = [np.array([[0, 0, 10, 10]]), np.array([[20, 20, 30, 30]])]
    # Image 1: a hit (0.9) and a miss (0.8); image 2: a hit (0.7) and a duplicate of it (0.6).
    detections = [(np.array([[0, 0, 10, 9], [50, 50, 60, 60]]), np.array([0.9, 0.8])),
                  (np.array([[21, 20, 30, 30], [20, 21, 30, 30]]), np.array([0.7, 0.6]))]
    got = average_precision(detections, truths)
    # Ranked: TP, FP, TP, FP -> precision 1, 1/2, 2/3, 1/2 at recall 1/2, 1/2, 1, 1;
    # the envelope is 1 up to recall 1/2 and 2/3 up to 1: AP = 1/2 + (2/3)/2.
    assert got["ap50"] == pytest.approx(0.5 + 1 / 3)
    assert (got["tp"], got["fp"], got["fn"]) == (2, 2, 0) and got["precision"] == 0.5 and got["recall"] == 1.0
    assert average_precision([(np.zeros((0, 4)), np.zeros(0))], [np.array([[0, 0, 1, 1]])])["ap50"] == 0.0
    assert iou(np.array([[0, 0, 2, 2]]), np.array([[1, 0, 3, 2]]))[0, 0] == pytest.approx(1 / 3)
    boxes = np.array([[0, 0, 10, 10], [1, 0, 10, 10], [20, 20, 30, 30]], dtype=float)
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.45).tolist() == [1, 2]


def constant_model(path, output: np.ndarray, size=(128, 160), meta: dict | None = None, batch: int = 1) -> None:
    """An ONNX model taking images (1, 3, H, W) whose output is ``output`` (plus 0 x the input)."""
    onnx = pytest.importorskip("onnx", reason="the yolo extra builds test models with onnx")
    from onnx import TensorProto, helper, numpy_helper

    nodes = [helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
             helper.make_node("Mul", ["m", "zero"], ["z"]),
             helper.make_node("Add", ["const", "z"], ["output0"])]
    graph = helper.make_graph(
        nodes, "constant",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [batch, 3, *size])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output.shape))],
        [numpy_helper.from_array(output.astype(np.float32), "const"),
         numpy_helper.from_array(np.zeros(1, np.float32), "zero")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in (meta or {}).items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))


def test_any_yolov8_style_onnx_runs_both_layouts_and_letterbox(tmp_path):
    # COCO-like raw output (1, 84, A): person (class 0) boxes in input pixels of 128 x 160.
    raw = np.zeros((1, 84, 100), dtype=np.float32)  # more anchors than channels, as in any real model
    raw[0, :4, 0] = [80, 64, 20, 10]      # person 0.9
    raw[0, :4, 1] = [81, 64, 20, 10]      # the same person, 0.8: suppressed
    raw[0, :4, 2] = [20, 30, 8, 8]        # person 0.3
    raw[0, :4, 3] = [100, 100, 8, 8]      # a car (class 2) 0.95: not a person
    raw[0, 4, :3] = [0.9, 0.8, 0.3]
    raw[0, 6, 3] = 0.95
    constant_model(tmp_path / "coco.onnx", raw)
    model = YoloOnnx(tmp_path / "coco.onnx")
    image = np.zeros((120, 160, 3), dtype=np.uint8)  # letterboxed with 4 rows above and below
    boxes = model.detect(image)
    assert [round(b.score, 2) for b in boxes] == [0.9, 0.3]
    assert (boxes[0].x0, boxes[0].y0, boxes[0].x1, boxes[0].y1) == pytest.approx((70, 55, 90, 65))
    assert (boxes[1].x0, boxes[1].y0) == pytest.approx((16, 22))
    # The same output transposed (N, A, 84), and an image twice the size (scaled by 1/2 in).
    constant_model(tmp_path / "t.onnx", raw.transpose(0, 2, 1).copy())
    big = YoloOnnx(tmp_path / "t.onnx").detect(np.zeros((240, 320, 3), dtype=np.uint8))
    assert (big[0].x0, big[0].y0, big[0].x1, big[0].y1) == pytest.approx((140, 110, 180, 130))
    # End-to-end (N, K, 6): x0, y0, x1, y1, score, class, already suppressed.
    e2e = np.array([[[10, 14, 30, 24, 0.7, 0], [0, 4, 5, 9, 0.9, 1], [1, 5, 2, 6, 0.1, 0]]], dtype=np.float32)
    constant_model(tmp_path / "e2e.onnx", e2e)
    found = YoloOnnx(tmp_path / "e2e.onnx").detect(image)
    assert len(found) == 1 and (found[0].x0, found[0].y0, found[0].score) == pytest.approx((10, 10, 0.7))
    with pytest.raises(ValueError, match="person_class = 90 is not one of them"):
        YoloOnnx(tmp_path / "coco.onnx", person_class=90).detect(image)
    with pytest.raises(ValueError, match="coco.onnx: person_class = -1: expected a class index"):
        YoloOnnx(tmp_path / "coco.onnx", person_class=-1)
    # A batch size baked into the file (2): three images go in two runs, the last padded.
    constant_model(tmp_path / "b2.onnx", np.concatenate([raw, raw]), batch=2)
    three = YoloOnnx(tmp_path / "b2.onnx").detect_many([image, image, image])
    assert [[round(b.score, 2) for b in found] for found in three] == [[0.9, 0.3]] * 3


def test_bad_yolo_models_are_named(tmp_path):
    with pytest.raises(ValueError, match="nope.onnx: no such YOLO ONNX file"):
        YoloOnnx(tmp_path / "nope.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx: cannot load the ONNX model"):
        YoloOnnx(tmp_path / "junk.onnx")
    constant_model(tmp_path / "flat.onnx", np.zeros((1, 10), dtype=np.float32))
    with pytest.raises(ValueError, match=r"flat.onnx: expected a detection output \(N, 4 \+ classes"):
        YoloOnnx(tmp_path / "flat.onnx")


def test_the_builtin_yolo_finds_persons_in_held_out_frames(frames):
    """The committed model on 40 frames of the test split (persons, distractors and flights it never saw),
    against today's pixel classifier on the same frames."""
    out, _ = frames
    images, truths = held_out_frames(out)
    yolo = evaluate(yolo_detect(YoloOnnx(BUILTIN_YOLO, confidence=0.001)), images, truths, levels=(0.0, 0.25))
    strict = evaluate(yolo_detect(YoloOnnx(BUILTIN_YOLO)), images, truths, levels=(0.0,))
    forest = evaluate(pixel_detect(detector.builtin_model()), images, truths, levels=(0.0,))
    # Measured on these 40 frames (2026-11-27, the model trained with degrees = 0): YOLO 0.88 /
    # 0.71 (25 % loss), at confidence 0.25 P 0.83, R 0.78; the forest 0.33 (the first model,
    # degrees = 180: 0.65 / 0.62, P 0.74, R 0.59). On all 240 test frames: docs/results/yolo.md.
    assert yolo["0.00"]["ap50"] >= 0.75, yolo  # issue #43's target on the shaded frames
    assert yolo["0.00"]["ap50"] > forest["0.00"]["ap50"] + 0.3, (yolo, forest)
    assert strict["0.00"]["precision"] >= 0.7 and strict["0.00"]["recall"] >= 0.65, strict
    assert yolo["0.25"]["ap50"] >= 0.55, yolo


def test_the_pixel_classifiers_boxes_are_its_regions_extents(frames):
    """The pixel classifier scored as a box detector: each detection's box is its region's
    extent and its score the region's mean probability, as found over the whole image; the
    detections the SAR loop publishes (no boxes) are the same regions."""
    from scipy.ndimage import label

    from caviar_plugins.tools.training.yolo_eval import pixel_boxes

    out, _ = frames
    images, _ = held_out_frames(out)
    model = detector.builtin_model()
    regions_seen = 0
    for image in images[:12]:
        mask, prob = model.mask(image)
        regions, n = label(mask)
        expected = []
        for k in range(1, n + 1):
            rows, cols = np.nonzero(regions == k)
            if len(rows) >= model.min_pixels:
                expected.append(([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], prob[rows, cols].mean()))
        boxes, scores = pixel_boxes(model, image)
        np.testing.assert_array_equal(boxes, np.array([b for b, _ in expected], dtype=float).reshape(-1, 4))
        np.testing.assert_allclose(scores, [sc for _, sc in expected], rtol=1e-12)
        plain = model.detect(image)
        assert [d.box for d in plain] == [None] * len(expected)
        assert [d.score for d in plain] == scores.tolist()
        regions_seen += len(expected)
    assert regions_seen >= 5


def test_the_sar_loop_with_yolo_rescues_the_person_in_view(tmp_path):
    from caviar_plugins.vision.camera import default_targets

    tx, ty = default_targets()[1]
    route_past(tmp_path, (tx, ty))
    cfg = write_config(tmp_path, episode(0.5, SAR_STAGES, seed=2) + waypoint_uav() + image_chain({"model": "yolo"}))
    log = caviar.Simulation.from_toml(cfg, out=tmp_path / "run").run()
    assert log.status["status"] == "completed"
    found = [d for row in log.topic("ai.detections")["detections"].to_list() for d in row]
    assert found and all(len(d["box"]) == 4 for d in found)
    near = 0
    for d in found:  # each box is a person: its centre's ground point is near a target
        x0, y0, x1, y1 = d["box"]
        assert 0 <= x0 < x1 <= 160 and 0 <= y0 < y1 <= 120 and 0.25 <= d["score"] <= 1
        assert (d["row"], d["col"]) == pytest.approx(((y0 + y1) / 2 - 0.5, (x0 + x1) / 2 - 0.5), abs=0.01)
        near += math.dist((d["ground"]["x"], d["ground"]["y"]), (tx, ty)) < 1.5
    assert near >= 0.8 * len(found), found
    the_rescue(log, (tx, ty))
    bad = write_config(tmp_path, open(cfg).read().replace('model = "yolo"', 'model = "missing.onnx"'), "bad.toml")
    with pytest.raises(caviar.RunError, match="missing.onnx: no such ONNX model file"):
        caviar.Simulation.from_toml(bad, out=tmp_path / "bad").run()


@pytest.mark.skipif(os.environ.get("CAVIAR_SKIP_TRAINING") == "1", reason="CAVIAR_SKIP_TRAINING=1")
def test_a_tiny_training_run_exports_an_onnx_model_that_runs_here(tmp_path, frames):
    """Ultralytics from the project's YAML, 1 epoch on 16 frames at 64 px, exported and run by
    onnxruntime: the pipeline of ``python -m caviar_plugins.tools.training.train_yolo``, not its quality."""
    pytest.importorskip("ultralytics", reason="training needs the yolo extra")
    src, _ = frames
    data = tmp_path / "frames"
    for split in ("train", "val"):
        for kind, ext in (("images", "png"), ("labels", "txt")):
            (data / kind / split).mkdir(parents=True)
            for p in sorted((src / kind / "test").glob(f"*.{ext}"))[:16 if split == "train" else 4]:
                (data / kind / split / p.name).write_bytes(p.read_bytes())
    (data / "data.yaml").write_text(f"path: {data}\ntrain: images/train\nval: images/val\nnames:\n  0: person\n")
    code = ("import pathlib, sys\n"
            "from caviar_plugins.tools.training import train_yolo as t\n"
            "w = t.train(pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), epochs=1, seed=0, batch=8, imgsz=64,"
            " workers=0)\n"
            "print(t.export(w, pathlib.Path(sys.argv[2]) / 'tiny.onnx', size=(64, 64)))\n")
    p = subprocess.run([sys.executable, "-c", code, str(data), str(tmp_path / "work")], capture_output=True,
                       text=True, timeout=600, env={**os.environ, "YOLO_OFFLINE": "1"})
    assert p.returncode == 0, p.stderr[-3000:]
    model = YoloOnnx(tmp_path / "work" / "tiny.onnx", confidence=0.0)
    assert model.size == (64, 64)
    out = model.session.run(None, {model.input: np.zeros((1, 3, 64, 64), np.float32)})[0]
    assert out.shape == (1, 5, 336)  # 4 box values + 1 class, over 16x16 + 8x8 + 4x4 anchors (strides 4, 8, 16)
    assert len(model.detect(np.zeros((120, 160, 3), np.uint8))) <= 336
