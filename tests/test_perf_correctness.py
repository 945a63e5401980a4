"""Issue #18 (faster steps): each fast path gives what the path it replaces gives."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from caviar_plugins.vision import VisualConfig, VisualScene, packet_loss
from caviar_plugins.vision import person_detector as detector


@pytest.fixture(scope="module")
def visual():
    return VisualScene(VisualConfig(), seed=1)


def views(visual, n: int, seed: int = 0) -> list[np.ndarray]:
    """Positions over the targets and along the route, at altitudes with both look-at
    roundings (two distinct rotation matrices occur among them)."""
    rng = np.random.default_rng(seed)
    targets = np.array(visual.cfg.targets)
    return [np.r_[targets[i % len(targets)] + rng.normal(0, 3, 2), rng.uniform(6.0, 14.0)] for i in range(n)]


def test_batched_camera_renders_the_per_uav_images_bit_for_bit(visual):
    pos = views(visual, 21)
    batched = visual.render_many(pos, chunk=8)  # several chunks, one partial
    for p, (image, labels) in zip(pos, batched, strict=True):
        ref_image, ref_labels = visual.render_labelled(p)
        np.testing.assert_array_equal(image, ref_image)
        np.testing.assert_array_equal(labels, ref_labels)
    assert any((lab >= 0).any() for _, lab in batched), "no person in view: the test shows nothing"
    assert len(visual._ray_cache) >= 1


@pytest.fixture(scope="module")
def model():
    return detector.train(count=30, seed=7)


def test_vectorised_detector_finds_what_the_per_image_detector_finds(visual, model):
    rng = np.random.default_rng(5)
    images = [im for im, _ in visual.render_many(views(visual, 12, seed=1))]
    images = [packet_loss(im, rate, rng) for im, rate in zip(images, [0.0, 0.01, 0.25, 0.5] * 3, strict=True)]
    batch = model.detect_many(images)
    single = [model.detect(im) for im in images]
    assert batch == single
    # Split into batches detected side by side (uneven chunks, more chunks than threads).
    with ThreadPoolExecutor(2) as pool:
        for chunks in (2, 5, 12, 40):
            assert model.detect_many(images, pool=pool, chunks=chunks) == single
    assert sum(len(d) for d in single) > 0, "nothing detected: the test shows nothing"


def test_the_forest_walked_tree_by_tree_gives_predict_probas_bits(visual, model):
    rng = np.random.default_rng(3)
    images = [packet_loss(im, rate, rng) for (im, _), rate in
              zip(visual.render_many(views(visual, 4, seed=2)), (0.0, 0.01, 0.25, 0.5), strict=True)]
    x = np.concatenate([detector.features(im) for im in images])
    np.testing.assert_array_equal(model.person_probability(x), model.forest.predict_proba(x)[:, 1])
    assert 0 < np.mean(model.person_probability(x) >= 0.5) < 0.5, "no person pixel: the test shows nothing"
    # A forest that predicts on several threads is left to scikit-learn (its sum's order varies).
    model.forest.n_jobs = 2
    try:
        calls = []
        real = model.forest.predict_proba
        model.forest.predict_proba = lambda rows: calls.append(len(rows)) or real(rows)
        model.person_probability(x[:10])
        assert calls == [10]
    finally:
        model.forest.n_jobs = 1
        del model.forest.predict_proba


def test_unique_rows_is_exact_even_with_hash_collisions(monkeypatch):
    rng = np.random.default_rng(0)
    words = rng.integers(0, 4, size=(5000, 3)).astype(np.uint64)
    first, inverse = detector.unique_rows(words)
    np.testing.assert_array_equal(words[first][inverse], words)
    assert len(first) == len(np.unique(words, axis=0))
    # A hash that collides everything: still exact.
    real_unique = np.unique

    def colliding(h, **kw):
        return real_unique(np.zeros_like(h), **kw)

    monkeypatch.setattr(detector.np, "unique", colliding)
    first, inverse = detector.unique_rows(words)
    np.testing.assert_array_equal(words[first][inverse], words)


# --- Ray tracing: path-buffer overflow, look-ahead -------------------------------

from caviar_plugins.radio import RadioConfig, RadioScene  # noqa: E402
from caviar_plugins.radio.scene import LookaheadTracer  # noqa: E402
from caviar_plugins.rt.settings import with_raytracing  # noqa: E402

FAST = dict(samples_per_src=20_000, max_depth=3, uav_mesh=False, threads=1)
P0, P1, P2 = np.array([-60.0, 20.0, 30.0]), np.array([-57.5, 20.0, 30.0]), np.array([-55.0, 20.0, 30.0])


def fresh(position, **kw) -> object:
    radio = RadioScene(with_raytracing(RadioConfig, **{**FAST, **kw}), seed=3)
    radio.place({"uav1": position})
    return radio.solve()["uav1"]


@pytest.fixture(scope="module")
def tracer():
    return LookaheadTracer(RadioScene(with_raytracing(RadioConfig, **FAST), seed=3), steps=2, tolerance_m=0.01)


def test_lookahead_cache_hit_is_the_channel_a_fresh_trace_gives(tracer):
    first = tracer.links({"uav1": P0}, {"uav1": [P1, P2]})["uav1"]
    assert tracer.solves == 1
    hit = tracer.links({"uav1": P1 + 0.004}, {})["uav1"]  # within the 1 cm tolerance
    assert tracer.solves == 1 and tracer.hits == 1
    np.testing.assert_array_equal(first.h, fresh(P0).h)
    ref = fresh(P1)
    # Same seed, one thread: the same rays and paths; the sum over paths may run in
    # another order in a solve with more receivers, so equal to float32 rounding.
    np.testing.assert_allclose(hit.h, ref.h, rtol=1e-5, atol=1e-6 * np.abs(ref.h).max())
    assert hit.best_pair == ref.best_pair and hit.n_paths == ref.n_paths


def test_a_ue_off_its_forecast_is_traced_on_demand(tracer):
    tracer.links({"uav1": P0}, {"uav1": [P1, P2]})
    solves = tracer.solves
    off = np.array([-40.0, 35.0, 25.0])
    link = tracer.links({"uav1": off}, {})["uav1"]
    assert tracer.solves == solves + 1
    ref = fresh(off)
    np.testing.assert_allclose(link.h, ref.h, rtol=1e-5, atol=1e-6 * np.abs(ref.h).max())


def test_lookahead_takes_moving_uav_bodies():
    """Look-ahead was refused with the UAV bodies; it now traces a body per forecast place
    (tests/test_solve_lookahead.py checks its links against step-by-step solves)."""
    from caviar_plugins.radio import SionnaLinkParams

    params = SionnaLinkParams(lookahead=True, uav_mesh=True)
    assert params.lookahead and params.uav_mesh and params.lookahead_steps == "auto"


def test_path_buffer_overflow_is_detected_and_reported():
    with pytest.warns(RuntimeWarning, match="path buffer overflowed"):
        link = fresh(P0, max_num_paths_per_src=5)
    assert link.paths_dropped > 0
    assert fresh(P0).paths_dropped == 0


def lookahead_run(tmp_path, name: str, lookahead: bool):
    from configs import run_config, traced_flight

    return run_config(tmp_path, traced_flight(3, lookahead=lookahead, lookahead_steps=3), out=name, name=f"{name}.toml")


def test_lookahead_runs_are_deterministic_and_solve_once_per_forecast(tmp_path):
    a, b = lookahead_run(tmp_path, "a", True), lookahead_run(tmp_path, "b", True)
    cols = ["step", "source", "topic", "text"]
    assert a.messages.select(cols).equals(b.messages.select(cols))
    for x, y in zip(a.decoded("communications.channel.uav1"), b.decoded("communications.channel.uav1"), strict=True):
        np.testing.assert_array_equal(x.data, y.data)
    assert len(a.topic("3D.mobility.forecast")) == 8
    # 8 steps, 1 + 3 positions per solve: solves at steps 0 and 4 only. The comm
    # module's timings show it: two slow steps.
    t = a.timings.filter(a.timings["module"] == "comm")["wall_s"].to_list()
    fast = sorted(t)[:6]
    assert max(fast) < 0.2 * min(sorted(t)[6:]), t
    # Every step's throughput equals tracing every step, to Monte Carlo-free float noise.
    plain = lookahead_run(tmp_path, "plain", False)
    np.testing.assert_allclose(a.topic("communications.throughput")["throughput"].to_numpy(),
                               plain.topic("communications.throughput")["throughput"].to_numpy(), rtol=1e-4)


# --- A hovering UAV: the same image, the same detections, no geometry update ------

def _plugin(cls, params, tmp_path):
    from caviar.plugin import Context

    plugin = cls()
    plugin.setup(Context(name=cls.__name__.lower(), params=params, seed=1, ts=0.5, steps=None, every=1, offset=0,
                         run_dir=tmp_path, config_dir=tmp_path))
    return plugin


def _positions(p) -> list:
    from caviar.plugin import Message
    from caviar_plugins.schema import POSITIONS

    return [Message(POSITIONS, {"UE_type": "UAV", "UE_Id": ue, "position": {"x": q[0], "y": q[1], "z": q[2]}})
            for ue, q in p.items()]


def test_a_uav_that_did_not_move_gets_its_last_image_without_a_render(visual, tmp_path):
    from caviar.plugin import Inbox
    from caviar_plugins.vision.camera import Camera

    a, b = views(visual, 2, seed=3)
    # Two UAVs: one hovers, then moves and comes back; the other moves every step.
    route = [{"u1": a, "u2": b}, {"u1": a, "u2": b + 1}, {"u1": a + [0.5, 0, 0], "u2": b + 2},
             {"u1": a + [0.5, 0, 0], "u2": b + 3}, {"u1": a, "u2": b + 4}]
    images = {}
    rendered = {}
    for still in (True, False):
        cam = _plugin(Camera, Camera.Params(still_frames=still), tmp_path)
        real, count = cam.visual.render_many, []

        def counting(positions, chunk=64, real=real, count=count):
            count.append(len(positions))
            return real(positions, chunk)

        cam.visual.render_many = counting
        images[still] = [dict(cam.step(0.5 * i, Inbox(_positions(p)))) for i, p in enumerate(route)]
        rendered[still] = count
    for got, ref in zip(images[True], images[False], strict=True):
        assert got.keys() == ref.keys() == {"3D.camera.u1", "3D.camera.u2"}
        for topic in got:
            np.testing.assert_array_equal(got[topic], ref[topic])
    # u1 is rendered at a (step 0), a + 0.5 (step 2) and a again (step 4: it moved away in between).
    assert rendered[True] == [2, 1, 2, 1, 2]
    assert rendered[False] == [2, 2, 2, 2, 2]


def test_an_image_seen_before_gets_its_detections_without_the_model(visual, model, tmp_path):
    from caviar.plugin import Inbox, Message
    from caviar_plugins.schema import per_ue

    path = tmp_path / "model.pkl"
    model.save(path)
    clean = visual.render(views(visual, 1, seed=1)[0])
    rng = np.random.default_rng(2)
    lossy = [packet_loss(clean, 0.25, rng) for _ in range(3)]
    # A hovering UAV's frames: whole, damaged, whole again...; the memo holds 2 images.
    frames = [clean, lossy[0], clean, clean, lossy[1], lossy[2], clean, lossy[0]]
    found, calls = {}, {}
    for keep in (2, 0):
        det = _plugin(detector.PersonDetector,
                      detector.PersonDetector.Params(model=str(path), seen_images=keep, workers=1), tmp_path)
        real, count = det.detector.detect_many, []

        def counting(images, pool=None, chunks=0, real=real, count=count):
            count.append(len(images))
            return real(images, pool, chunks)

        det.detector.detect_many = counting
        found[keep] = [list(det.step(0.5 * i, Inbox(_positions({"u": [0.0, 0.0, 9.0]}) +
                                                    [Message(per_ue("ai.images", "u"), im)])))
                       for i, im in enumerate(frames)]
        calls[keep] = sum(count)
        assert len(det.seen.get("u", {})) == keep
    assert found[2] == found[0]
    assert sum(m[0][1]["count"] for m in found[0]) > 0, "nothing detected: the test shows nothing"
    # Model runs with a memo of 2: clean, lossy0, (clean, clean seen), lossy1, lossy2 (evicts
    # clean), clean, lossy0 (evicted by lossy2 then clean) = 6 of 8.
    assert (calls[2], calls[0]) == (6, 8)
    with pytest.raises(ValueError, match="seen_images"):
        _plugin(detector.PersonDetector, detector.PersonDetector.Params(model=str(path), seen_images=-1), tmp_path)


def test_a_body_that_did_not_move_leaves_the_geometry_alone(monkeypatch):
    from sionna.rt.scene_object import SceneObject

    radio = RadioScene(with_raytracing(RadioConfig, **{**FAST, "uav_mesh": True}), seed=1)
    moves = []
    prop = SceneObject.position
    monkeypatch.setattr(SceneObject, "position", property(prop.fget, lambda obj, v: (moves.append(list(v)),
                                                                                      prop.fset(obj, v))))
    for p in (P0, P0, P1, P1, P0):
        radio.place({"u": p})
    assert moves == [P0.tolist(), P1.tolist(), P0.tolist()]
    np.testing.assert_allclose(np.array(radio.bodies["u"].position).ravel(), P0)
