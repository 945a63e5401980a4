"""The timing items ``scripts/gpu_check.py`` runs in its own process (seconds each, their errors
reported in their rows): the person detectors and a material fit, each on the machine's device."""

from __future__ import annotations

import statistics
import time


def yolo_times(frames: int = 16, reps: int = 20) -> dict:
    """The person detector's YOLO on ``frames`` twin-sized frames (160 x 120) a batch, per
    frame: onnxruntime (as installed) and torch on its device (a CUDA graph on a GPU), each
    ``cold`` (the first batch: loading, capture) and ``warm`` (median of ``reps``), and how far
    torch's raw outputs are from onnxruntime's on the same frames."""
    import numpy as np

    from caviar_plugins.vision.yolo import BUILTIN_YOLO, YoloOnnx

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(frames)]
    out: dict = {"frames_per_batch": frames}
    raws = {}
    for runtime in ("onnxruntime", "torch"):
        t0 = time.perf_counter()
        model = YoloOnnx(BUILTIN_YOLO, runtime=runtime)
        batch = np.stack([model.letterbox(im)[0] for im in images]).transpose(0, 3, 1, 2).astype(np.float32) / 255
        raws[runtime] = model.run(batch)
        cold = time.perf_counter() - t0
        warm = []
        for _ in range(reps):
            t0 = time.perf_counter()
            model.detect_many(images)
            warm.append(time.perf_counter() - t0)
        out[runtime] = {"device": str(model.graph.device) if model.graph is not None else "onnxruntime "
                        f"{model.session.get_providers()[0]}", "cold_s": round(cold, 3),
                        "warm_ms_per_frame": round(1e3 * statistics.median(warm) / frames, 3)}
    out["torch_vs_onnxruntime_max_abs"] = {"boxes_px": float(np.abs(raws["torch"][:, :4] - raws["onnxruntime"][:,
                                                                                                               :4]).max()),
                                           "scores": float(np.abs(raws["torch"][:, 4] - raws["onnxruntime"][:,
                                                                                                            4]).max())}
    return out


def forest_times(frames: int = 20) -> dict:
    """The main job's own detector (the builtin pixel forest, a step's one frame at a time) per
    frame: scikit-learn's walk on the CPU and torch's on its device, each warm (median of
    ``frames`` frames after one), and whether their detections are the same (they must be)."""
    import numpy as np

    from caviar_plugins.vision.person_detector import PixelDetector, builtin_model
    from caviar_plugins.vision.yolo import torch_device_of

    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(frames + 1)]
    cpu = builtin_model()
    device = PixelDetector(cpu.forest, cpu.min_pixels, cpu.threshold).to_device(torch_device_of("auto"))
    out: dict = {"device": str(device.on_device.device)}
    found = {}
    for name, detector in (("scikit_learn", cpu), ("torch", device)):
        times, found[name] = [], []
        for im in images:
            t0 = time.perf_counter()
            found[name].append(detector.detect_many([im]))
            times.append(time.perf_counter() - t0)
        out[f"{name}_ms_per_frame"] = round(1e3 * statistics.median(times[1:]), 3)
    out["same_detections"] = found["scikit_learn"] == found["torch"]
    return out


def fit_times(n: int = 40, truth: float = 3 * 5.24) -> dict:
    """A material fit on the machine's Dr.Jit backend (issue #56): Sionna's street canyon,
    ``n`` receivers, concrete's permittivity ``truth`` (3x ITU's) hidden in measurements with
    0.3 dB of noise, learned back (a search, Levenberg–Marquardt, one restart): the fit's wall
    time (its traces included) over its guesses, and the learned value against the truth
    (within 5 % on the CPU, tests/test_fit_scene.py)."""
    import dataclasses

    import numpy as np

    from caviar_plugins.rt.materials import apply_materials
    from caviar_plugins.rt.received_power import ReceivedPower
    from caviar_plugins.rt.scene import sionna_rt
    from caviar_plugins.twin.fit import FIT_RAYS, FitSettings, fit_materials
    from caviar_plugins.twin.measurements import Measurements

    rt = sionna_rt()
    rays = dataclasses.replace(FIT_RAYS, los=False, max_depth=2, samples_per_src=200_000)
    tx = np.array([-40.0, 0.0, 12.0])
    rng = np.random.default_rng(5)
    rx = np.c_[rng.uniform(-55, 55, n), rng.uniform(-8, 8, n), np.full(n, 1.5)]

    def street():
        scene = rt.load_scene(rt.scene.simple_street_canyon)
        scene.frequency = 3.5e9
        return scene

    hidden = street()
    model = ReceivedPower(hidden, rays, seed=0)
    apply_materials(hidden, {"concrete": {"relative_permittivity": truth}})
    model.place(rx, tx[None])
    pairs = np.c_[np.arange(n), np.zeros(n, dtype=int)]
    power = model.predict(pairs, 30.0) + rng.normal(0.0, 0.3, n)
    ok = np.isfinite(power)
    data = Measurements(np.arange(ok.sum(), dtype=float), rx[ok], np.tile(tx, (int(ok.sum()), 1)), power[ok],
                        np.full(int(ok.sum()), 30.0), 3.5e9, 20e6)
    settings = FitSettings(learn=("relative_permittivity",), materials=("concrete",), iterations=20, holdout=0.25,
                           noise_db=0.3, search_sweeps=2, restarts=1)
    t0 = time.perf_counter()
    result = fit_materials(street(), data, settings, rays)
    wall = time.perf_counter() - t0
    learned = result.learned[("concrete", "relative_permittivity")]
    return {"receivers": int(ok.sum()), "rays": rays.samples_per_src, "wall_s": round(wall, 2),
            "guesses": result.cost["field_evaluations"], "traces": result.cost["traces"],
            "ms_per_guess": round(1e3 * wall / max(result.cost["field_evaluations"], 1), 2),
            "learned": round(learned, 3), "truth": truth, "relative_error": round(learned / truth - 1, 4),
            "held_out_rmse_db": result.rmse_db["held_out"]}
