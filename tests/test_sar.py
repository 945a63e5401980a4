"""Search-and-rescue plugins, each alone with small settings, and a short all-in-loop episode."""

import itertools
import math

import numpy as np
import pytest

import caviar
from caviar_plugins import beam_selection
from caviar_plugins.radio import RadioConfig, RadioScene
from caviar_plugins.rt.settings import with_raytracing
from caviar_plugins.schema import read_position
from caviar_plugins.vision import VisualConfig, VisualScene, loss_for_throughput, packet_loss, psnr
from caviar_plugins.vision import person_detector as detector
from configs import (
    SAR_STAGES,
    episode,
    image_chain,
    module,
    output,
    route_past,
    run_config,
    sionna_link,
    the_rescue,
    waypoint_uav,
)
from conftest import write_config


def assert_publishes_declared(log, plugins: dict[str, str]) -> None:
    """Every topic a module published matches a pattern of its plugin's ``publishes``
    (``plugins``: module name -> entry-point name)."""
    from importlib.metadata import entry_points

    from caviar.topics import matches

    classes = {ep.name: ep.load() for ep in entry_points(group="caviar.plugins") if ep.name in plugins.values()}
    seen = set()
    for source, topic in log.messages.select("source", "topic").unique().iter_rows():
        if source in plugins:
            declared = classes[plugins[source]].publishes
            assert any(matches(p, topic) for p in declared), f"{source} published {topic}, not in {declared}"
            seen.add(source)
    assert seen, "none of the modules published anything"


def test_every_plugin_declares_what_it_publishes(tmp_path):
    from importlib.metadata import entry_points

    from conftest import ROOT

    ours = [ep for ep in entry_points(group="caviar.plugins") if ep.value.startswith("caviar_plugins.")]
    # The SAR and radio plugins; other domains (traffic, ...) add their own.
    assert {"waypoint-flight", "random-waypoint-flight", "free-space-link", "sionna-link", "link-monitor", "camera",
            "image-link", "person-detector", "beam-selector", "beam-dataset", "mission"} <= {ep.name for ep in ours}
    for ep in ours:
        publishes = ep.load().publishes
        assert isinstance(publishes, tuple) and publishes and all(isinstance(t, str) for t in publishes), ep.name
    log = caviar.Simulation.from_toml(ROOT / "blueprints" / "quickstart" / "config.toml", out=tmp_path / "run",
                                      overrides={"episode.steps": 20}).run()
    assert_publishes_declared(log, {"uav": "waypoint-flight", "comm": "free-space-link", "monitor": "link-monitor"})
    assert "ai.link.report" in set(log.messages["topic"])


@pytest.fixture(scope="module")
def visual():
    return VisualScene(VisualConfig(), seed=1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A detector trained on 60 rendered frames (the builtin one uses 240)."""
    model = detector.train(count=60, seed=7)
    path = tmp_path_factory.mktemp("model") / "detector.pkl"
    model.save(path)
    return model, path


def test_camera_sees_a_target_where_the_geometry_says(visual):
    tx, ty = visual.cfg.targets[2]
    image, labels = visual.render_labelled([tx + 2.0, ty - 1.5, 9.0])
    assert image.dtype == np.uint8 and image.shape == (120, 160, 3)
    rows, cols = np.nonzero(labels == 2)
    assert len(rows) > 50
    # The person's pixels map back to its ground position through the nadir camera model.
    g = detector.pixel_to_ground(rows.mean(), cols.mean(), image.shape, (tx + 2.0, ty - 1.5, 9.0), 70.0)
    assert math.dist((g["x"], g["y"]), (tx, ty)) < 0.4
    # Far from every target no person is in view.
    _, empty = visual.render_labelled([tx + 40.0, ty + 40.0, 9.0])
    assert (empty >= 0).sum() == 0


def test_packet_loss_follows_the_paper_table_and_psnr(visual):
    assert [loss_for_throughput(x) for x in (90, 60.01, 60, 30.01, 30, 0)] == [0.01, 0.01, 0.25, 0.25, 0.5, 0.5]
    image = visual.render(visual.cfg.targets[0] + [9.0])
    rng = np.random.default_rng(0)
    assert psnr(image, packet_loss(image, 0.0, rng)) == float("inf")
    results = {}
    for rate in (0.01, 0.25, 0.5):
        values = [packet_loss(image, rate, rng) for _ in range(40)]
        lost = np.mean([np.mean(np.all(v == 0, axis=2)) for v in values])
        assert lost == pytest.approx(rate, abs=0.35 * rate + 0.01)
        # A 160 x 120 frame is only 42 packets: pool the error over the trials.
        mse = np.mean([np.mean((image.astype(float) - v) ** 2) for v in values])
        results[rate] = 10 * np.log10(255**2 / mse)
    # The paper: ~26.4, ~12.4 and ~9.4 dB.
    assert 21 < results[0.01] < 32 and 10 < results[0.25] < 15 and 7 < results[0.5] < 12


def test_detector_precision_and_recall_on_held_out_frames(trained):
    model, path = trained
    report = detector.evaluate(detector.PixelDetector.load(path), count=40, seed=99)
    clean = report["0.00"]
    assert clean["precision"] >= 0.9 and clean["recall"] >= 0.9, report
    tp, fp = sum(r["tp"] for r in report.values()), sum(r["fp"] for r in report.values())
    assert tp / (tp + fp) >= 0.9, report  # over all loss rates (few frames each)


def test_mission_stops_for_the_upload_and_counts_each_person_once(tmp_path):
    log = run_config(tmp_path, episode(1.0, ["sensors", "mission"], steps=6)
                     + module("script", "sensors", "sample_plugins:ScriptedDetections")
                     + module("mission", "mission", "mission"))
    hover = log.topic("mission.hover")
    # Detections at steps 1 (person A), 2 (A again, 3 m away: same), 3 (person B at 80 Mbit/s).
    assert hover["step"].to_list() == [1, 3]
    assert hover["seconds"].to_list() == pytest.approx([320 / 40.0, 320 / 80.0])
    result = log.topic("mission.result").row(0, named=True)
    assert result["rescued"] == 2 and result["mission_time_s"] == 5.0


def test_beam_selection_methods(tmp_path):
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=10_000, uav_mesh=False))
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-250, 250, 60), rng.uniform(-100, 200, 60), np.full(60, 9.23)]
    radio.place({f"p{i}": p for i, p in enumerate(pts)})
    best = np.array([link.best_pair for link in radio.solve().values()])
    tree = beam_selection.train(pts, best)
    assert tree.get_depth() <= 15 and np.mean(tree.predict(pts) == best) > 0.9  # fits its training set
    scores = tree.predict_proba(pts)
    top = beam_selection.top_k_accuracy(scores, tree.classes_, best, [1, 5, 256])
    assert top[1] <= top[5] <= top[256] == 1.0
    beam_selection.save(tree, tmp_path / "tree.pkl")

    base = (episode(0.5, ["mobility", "ai"], steps=4, seed=9)
            + module("uav", "mobility", "waypoint-flight", {"waypoints": "central_park_path0_scene.csv",
                                                            "frame": "scene"})
            + module("beams", "ai", "beam-selector"))
    for method, extra in (("random", ""), ("tree", ', model = "tree.pkl"'), ("oracle", "")):
        cfg = write_config(tmp_path, base + f'params = {{ method = "{method}"{extra} }}\n', f"{method}.toml")
        log = caviar.Simulation.from_toml(cfg, out=tmp_path / method).run()
        picks = log.topic("ai.beam.selection") if method != "oracle" else None
        if method == "oracle":
            assert "ai.beam.selection" not in set(log.messages["topic"])
        else:
            assert picks.height == 4 and all(0 <= p < 256 for p in picks["beam_pair"])
        if method == "tree":
            xyz = np.array([read_position(row) for row in log.topic("3D.mobility.positions").iter_rows(named=True)])
            assert picks["beam_pair"].to_list() == tree.predict(xyz).tolist()
    again = caviar.Simulation.from_toml(tmp_path / "random.toml", out=tmp_path / "random2").run()
    assert again.topic("ai.beam.selection")["beam_pair"].to_list() == \
        caviar.load_run(tmp_path / "random").topic("ai.beam.selection")["beam_pair"].to_list()
    with pytest.raises(caviar.ConfigError, match="modules.beams.params: method 'tree' needs `model`"):
        caviar.Simulation.from_toml(write_config(tmp_path, base + 'params = { method = "tree" }\n', "bad.toml"))


def test_short_all_in_loop_episode_rescues_the_person_in_view(tmp_path, trained, visual):
    _, model = trained
    tx, ty = visual.cfg.targets[1]
    route_past(tmp_path, (tx, ty))
    beams_and_rays = module("beams", "ai", "beam-selector", {"method": "oracle"}) + sionna_link(publish_channels=False)
    log = run_config(tmp_path, episode(0.5, ["mobility", "camera", "ai", *SAR_STAGES[2:]], seed=2) + waypoint_uav()
                     + image_chain({"model": model.as_posix()}, camera={"save": True}, radio=beams_and_rays))
    assert log.status["status"] == "completed"
    quality = log.topic("ai.image_quality")
    assert quality.height == log.status["steps_done"]
    assert set(quality["loss_rate"]) <= {0.01, 0.25, 0.5}
    r = the_rescue(log, (tx, ty))
    assert r["hover_s"] == pytest.approx(min(320 / r["throughput"], 600.0))
    # The hover shows in the flight: the UAV stood still after the rescue.
    xs = [p["x"] for p in log.topic("3D.mobility.positions")["position"].to_list()]
    assert sum(1 for a, b in itertools.pairwise(xs) if a == b) >= 2
    result = log.topic("mission.result").row(0, named=True)
    flight = 16.0 / 5.0
    assert result["rescued"] == 1 and result["mission_time_s"] >= flight + min(r["hover_s"], 600) - 1.0
    assert len(list((tmp_path / "run" / "artifacts" / "camera").glob("uav1-*.png"))) == log.status["steps_done"]
    assert_publishes_declared(log, {"uav": "waypoint-flight", "camera": "camera", "beams": "beam-selector",
                                    "comm": "sionna-link", "link": "image-link", "detector": "person-detector",
                                    "mission": "mission"})


def test_beam_dataset_blueprint_and_tree_training(tmp_path, cli):
    import json
    import subprocess
    import sys

    from caviar_plugins.beam_selection import load
    from conftest import ROOT

    bp = ROOT / "blueprints" / "beam-dataset"
    small = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "-q"]
    cli("run", bp / "config.toml", "--out", "train", "--set", "episode.steps=24", *small, check=0)
    cli("run", bp / "test-flight.toml", "--out", "test", "--set", "episode.steps=8", *small, check=0)
    data = load(tmp_path / "train")
    assert_publishes_declared(caviar.load_run(tmp_path / "train"),
                              {"uav": "random-waypoint-flight", "comm": "sionna-link", "dataset": "beam-dataset"})
    assert_publishes_declared(caviar.load_run(tmp_path / "test"), {"uav": "waypoint-flight"})
    assert data["position"].shape == (24, 3) and data["gains"].shape == (24, 4, 64)
    assert np.array_equal(data["best_pair"], data["gains"].reshape(24, -1).argmax(axis=1))
    hops = np.linalg.norm(np.diff(data["position"], axis=0), axis=1)
    assert np.all(hops <= 2.5 + 1e-9)  # 5 m/s at Ts = 0.5 s, through random waypoints
    p = subprocess.run([sys.executable, "-m", "caviar_plugins.tools.training.train_tree", "--train", "train",
                        "--test", "test", "--out", "tree.pkl", "--report-dir", "report"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    report = json.loads((tmp_path / "report" / "topk.json").read_text())
    val = [report["validation_topk"][str(k)] for k in beam_selection.K_VALUES]
    test = [report["test_topk"][str(k)] for k in beam_selection.K_VALUES]
    assert val == sorted(val) and test == sorted(test)  # top-K grows with K
    assert report["fit"] + report["validation"] == report["nlos_samples"] == int((~data["los"].astype(bool)).sum())
    assert (tmp_path / "report" / "topk.png").exists() and "| 100 |" in (tmp_path / "report" / "topk.md").read_text()


def test_a_user_supplied_onnx_model_detects_like_the_original(tmp_path, trained, visual):
    model, _ = trained
    path = tmp_path / "detector.onnx"
    detector.export_onnx(model, path)
    onnx = detector.PixelDetector.load(path)
    agree, persons = [], 0
    for x, y in visual.cfg.targets:
        image = visual.render([x + 1.0, y - 1.0, 9.0])
        a, b = model.mask(image)[0], onnx.mask(image)[0]
        agree.append(np.mean(a == b))
        persons += len(onnx.detect(image)) > 0
    assert min(agree) > 0.999 and persons == len(visual.cfg.targets)
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="cannot load the ONNX model"):
        detector.PixelDetector.load(tmp_path / "bad.onnx")


def test_the_detector_plugin_loads_an_onnx_file_once_whichever_kind_it_is(tmp_path, trained, monkeypatch):
    """An ONNX pixel classifier and an ONNX YOLO model, given to the detector plugin by path:
    each file is loaded into onnxruntime once, and the plugin tells them apart by their input
    (features (N, 10) or images (N, 3, H, W))."""
    import onnxruntime as ort

    from caviar.plugin import Context
    from caviar_plugins.vision.yolo import BUILTIN_YOLO

    model, _ = trained
    pixel = tmp_path / "detector.onnx"
    detector.export_onnx(model, pixel)
    loads = []
    session = ort.InferenceSession
    monkeypatch.setattr(ort, "InferenceSession",
                        lambda path, *a, **kw: (loads.append(path), session(path, *a, **kw))[1])
    kinds = {}
    for path in (pixel, BUILTIN_YOLO):
        plugin = detector.PersonDetector()
        plugin.setup(Context(name="detector", params=detector.PersonDetector.Params(model=str(path)), seed=1, ts=1.0,
                             steps=None, every=1, offset=0, run_dir=tmp_path, config_dir=tmp_path))
        kinds[path.name] = type(plugin.detector).__name__, type(getattr(plugin.detector, "forest", None)).__name__
        plugin.teardown()
    assert loads == [str(pixel), str(BUILTIN_YOLO)]
    assert kinds == {"detector.onnx": ("PixelDetector", "OnnxPixelModel"), BUILTIN_YOLO.name: ("YoloPersonDetector",
                                                                                               "NoneType")}


def test_detector_threads_find_the_same_people_as_one_thread(tmp_path, trained, visual):
    """Three UAVs over three targets: the detector's images of a step are classified side
    by side, and the recorded detections are those of one thread."""
    _, model = trained
    uavs = ""
    for i, target in enumerate(visual.cfg.targets[:3]):
        route_past(tmp_path, target, half=2.0, z=9.0, name=f"route{i}.csv")
        uavs += waypoint_uav(f"route{i}.csv", 2.0, name=f"uav{i}", ue_id=f"uav{i}")
    cfg = write_config(tmp_path, episode(0.5, SAR_STAGES[:-1], steps=4, seed=3) + uavs
                       + image_chain({"model": model.as_posix(), "workers": 3}, mission=False))
    runs = {}
    for workers in (1, 3):
        sim = caviar.Simulation.from_toml(cfg, out=tmp_path / f"run-{workers}",
                                          overrides={"modules.detector.params.workers": workers})
        runs[workers] = sim.run().topic("ai.detections")
    assert runs[1].height == 4 * 3
    assert runs[1]["count"].sum() >= 6  # the people below are found (through packet loss)
    assert runs[1].equals(runs[3])
    bad = write_config(tmp_path, cfg.read_text().replace("workers = 3", "workers = -1"), "bad.toml")
    with pytest.raises(Exception, match="workers"):
        caviar.Simulation.from_toml(bad, out=tmp_path / "bad").run()


def test_the_camera_rides_only_on_the_ue_types_it_is_given(tmp_path):
    """``ue_types = ["UAV"]``: a city's cars publish positions too, but only the UAV gets a
    camera (and an image a step)."""
    ues = [{"id": "uav1", "type": "UAV", "start": [0.0, 0.0, 40.0], "end": [10.0, 0.0, 40.0], "speed": 5.0},
           {"id": "car1", "type": "car", "start": [5.0, 5.0, 0.0], "end": [5.0, 25.0, 0.0], "speed": 5.0}]
    log = run_config(tmp_path, episode(0.5, ["mobility", "camera"], steps=2)
                     + output(analysis=["3D.camera.*", "3D.camera.*.file", "3D.camera.*.depth"])
                     + module("ues", "mobility", "sample_plugins:LineMover", {"ues": ues})
                     + module("camera", "camera", "camera", {"ue_types": ["UAV"], "distractors": 0}), name="cam.toml")
    assert sorted(set(log.messages["topic"].to_list()) - {"3D.mobility.positions"}) == ["3D.camera.uav1"]
    assert len(log.decoded("3D.camera.uav1")) == 2
