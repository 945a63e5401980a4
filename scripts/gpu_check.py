"""Checks a machine, a GPU one first of all (issue #39): every blueprint for a few steps, then
the timing items; prints one table and writes ``docs/results/gpu.json`` with the device named.

    python3 scripts/gpu_check.py [--steps 6] [--out docs/results/gpu.json] [--no-timings]

``scripts/gpu-check.sh`` runs it with the right interpreter. It runs anywhere: on a CPU-only
machine it checks the same blueprints on Dr.Jit's LLVM backend and names that device. Per
blueprint: steps done, ``ok`` or the error (the run's own words, from run.json), T_p/T_v, and
the GPU's mean utilisation and peak memory over the run's modules (the core samples them with
nvidia-ml-py; empty without a GPU). Where SUMO is missing (it cannot travel to the lent GPU
machine), a blueprint with SUMO traffic runs on that traffic as recorded here
(``--record-traffic``, replayed with ``caviar.replay``), and its row says so; a blueprint whose
other packages are missing is reported as skipped, with the reason. Timing items:

- one solve of the SAR route with 1 and 10 UAVs at 1e6 samples, cold (the process's first)
  and warm (median of 8 after 5 more), with the shoot cache as the backend's default chooses it;
- the main job: ``caviar-core run blueprints/sar/config.toml`` to its end, twice: with empty
  kernel caches (:data:`KERNEL_CACHES`, all under one new folder), then again with what the
  first run left there; each its wall time from the command's start (Python, plugins and
  kernel compilation included), T_p/T_v and the mission's outcome, held to a CPU run
  (:func:`agreement`);
- YOLO through onnxruntime and through torch on its device (:func:`yolo_times`), and the main
  job's own detector, the pixel forest, walked by scikit-learn and by torch (:func:`forest_times`);
- a material fit (``fit-scene``'s, :func:`fit_times`): the street canyon's concrete learned back
  on the backend, its time per guess and the learned value against the hidden truth;
- the radio network at scale: the ``radio-network`` plugin with 21 cells (7 sites × 3
  sectors) and 100, then 1,000 UEs, 0.5 ms slots, 0.1 s steps, ray tracing every 1 s, beams
  and the uplink, full buffers, the UEs' reports as one table a step (``ue_reports = "table"``,
  the setting for a thousand UEs; until 2026-11-29 a message a UE), :data:`NETWORK_GROUPS_PER_CALL`
  groups of slots a compiled call (since 2026-11-29 afternoon; one before) (``benches/bench_network.py
  --plugin-only``): T_p/T_v of the steps after the first (the first traces and compiles; its
  time is reported too).

The main job and the network items run in their own processes under a time limit
(``--item-timeout``), so that one that hangs or crawls is reported as such and the check still
ends; the solves and YOLO (seconds) run in this process, their errors reported in their rows.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

from gpu_timings import fit_times, forest_times, yolo_times

ROOT = pathlib.Path(__file__).resolve().parent.parent
BLUEPRINTS = ROOT / "blueprints"
CORE = [sys.executable, "-m", "caviar.cli"]


def blueprint_runs(steps: int) -> dict[str, tuple[pathlib.Path, list[str], list[str]]]:
    """name -> (config, extra --set overrides, modules it needs importable)."""
    return {
        "quickstart": (BLUEPRINTS / "quickstart/config.toml", [], []),
        "raytraced": (BLUEPRINTS / "raytraced/config.toml", [], ["sionna.rt"]),
        "sar": (BLUEPRINTS / "sar/config.toml", [], ["sionna.rt"]),
        "sar-paper": (BLUEPRINTS / "sar-paper/config.toml", [], ["sionna.rt"]),
        "osm-city": (BLUEPRINTS / "osm-city/config.toml", [], ["sionna.rt"]),
        "osm-traffic": (BLUEPRINTS / "osm-traffic/config.toml", [], ["sionna.rt", "libsumo"]),
        "network-city": (BLUEPRINTS / "network-city/config.toml", [], ["sionna.rt", "sionna.sys", "libsumo"]),
        "live-uav": (BLUEPRINTS / "live-uav/config.toml", [], ["sionna.rt", "pymavlink"]),
        "beam-gym": (BLUEPRINTS / "beam-gym/config.toml", [], ["sionna.rt"]),
        "network-38901": (BLUEPRINTS / "network-38901/config.toml", [], ["sionna.sys"]),
        "uav-energy": (BLUEPRINTS / "uav-energy/config.toml", [], ["sionna.rt"]),
        "lidar-city": (BLUEPRINTS / "lidar-city/config.toml", [], ["sionna.rt", "libsumo"]),
        "beam-lidar": (BLUEPRINTS / "beam-lidar/config.toml", [], ["sionna.rt"]),
        "beam-dataset": (BLUEPRINTS / "beam-dataset/config.toml", [], ["sionna.rt"]),
        "sar-ns3": (BLUEPRINTS / "sar-ns3/config.toml", [], ["sionna.rt", "ns"]),
        "self-calibrating": (BLUEPRINTS / "self-calibrating/config.toml", [], ["sionna.rt"]),
    }
    # Not here: legacy (a module of the original CAVIAR over an outside NATS server: nothing
    # of it runs on a GPU).


TRAFFIC_RUNS = ROOT / "docs/results/gpu-check-traffic"
"""Recorded runs of the blueprints with SUMO traffic (``--record-traffic``, 12 steps each): on
a machine without SUMO (it cannot travel to the lent GPU machine) the check replays their
``sumo-traffic`` module's messages with ``caviar.replay`` instead, and says so."""


def sumo_module(config: pathlib.Path) -> tuple[str, str] | None:
    """(name, stage) of the configuration's ``sumo-traffic`` module, if it has one."""
    import tomllib

    for name, table in tomllib.loads(config.read_text()).get("modules", {}).items():
        if table.get("plugin") == "sumo-traffic":
            return name, table["stage"]
    return None


def replaying_traffic(config: pathlib.Path, name: str, stage: str, run: pathlib.Path) -> pathlib.Path:
    """A copy of ``config`` beside it (its relative paths hold) whose module ``name`` replays
    what that module published in the recorded ``run``, in place of SUMO."""
    keep, skipping = [], False
    for line in config.read_text().splitlines():
        if line.lstrip().startswith("["):
            table = line.strip().strip("[]").strip()
            skipping = table == f"modules.{name}" or table.startswith(f"modules.{name}.")
        if not skipping:
            keep.append(line)
    keep += ["", f"[modules.{name}]", f'stage = "{stage}"', 'plugin = "caviar.replay"', f"[modules.{name}.params]",
             f"run = {json.dumps(str(run))}", f'sources = ["{name}"]', ""]
    out = config.with_name(f".gpu-check-{config.stem}-replay.toml")
    out.write_text("\n".join(keep))
    return out


def keep_only_traffic(run: pathlib.Path, module: str) -> None:
    """Of a recorded run, only what a replay of ``module`` reads: its messages (and run.json,
    the run's own account): the rest (other modules' messages, artifacts) would only weigh."""
    import shutil

    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    table = pq.read_table(run / "messages.parquet")
    pq.write_table(table.filter(pc.equal(table["source"], module)), run / "messages.parquet")
    for f in run.iterdir():
        if f.name not in ("messages.parquet", "run.json"):
            shutil.rmtree(f) if f.is_dir() else f.unlink()


def record_traffic(steps: int = 12) -> int:
    """Records each SUMO blueprint's first ``steps`` steps to :data:`TRAFFIC_RUNS` (here, where
    SUMO is installed), for :func:`replaying_traffic` on a machine without it."""
    import shutil

    for name, (config, _, _) in blueprint_runs(steps).items():
        if sumo_module(config) is None:
            continue
        out = TRAFFIC_RUNS / name
        shutil.rmtree(out, ignore_errors=True)
        _, error = command([*CORE, "run", str(config), *length(config, steps), "--out", str(out), "-q"], None)
        if error is not None:
            print(f"{name}: {error}")
            return 1
        keep_only_traffic(out, sumo_module(config)[0])
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        print(f"{name}: {steps} steps recorded in {out.relative_to(ROOT)} ({size / 1024:.0f} KiB)")
    return 0


def device() -> dict:
    """The machine: CPU, GPU, the Dr.Jit variant Sionna RT chooses and torch's device
    (:func:`caviar_plugins.machine.describe`)."""
    from caviar_plugins.machine import describe

    return describe()


def missing(modules: list[str]) -> str | None:
    for m in modules:
        try:
            if importlib.util.find_spec(m) is None:
                return f"{m} is not installed"
        except (ImportError, ValueError):
            return f"{m} is not installed"
    return None


def command(cmd: list[str], timeout_s: float | None, env: dict[str, str] | None = None) -> tuple[str, str | None]:
    """Runs ``cmd`` in the checkout under a time limit (with ``env`` added to the environment):
    (its output, None) when it succeeds, else (its output, its own last line of error, or the
    time limit it ran past)."""
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT,
                           env=None if env is None else {**os.environ, **env})
    except subprocess.TimeoutExpired:
        return "", f"timed out after {timeout_s:.0f} s"
    if p.returncode == 0:
        return p.stdout, None
    return p.stdout, (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]


def run_blueprint(name: str, config: pathlib.Path, sets: list[str] | tuple[str, ...], steps: int | None,
                  work: pathlib.Path, timeout_s: float, env: dict[str, str] | None = None) -> dict:
    """One blueprint for ``steps`` steps (None: to its end): its row of the table."""
    from caviar.rundir import RunDir

    out = work / name
    cmd = [*CORE, "run", str(config), *([] if steps is None else length(config, steps)),
           *[x for s in sets for x in ("--set", s)], "--out", str(out), "-q"]
    sender = None
    if name == "live-uav":  # its vehicle: the scripted MAVLink sender
        sender = subprocess.Popen([sys.executable, str(BLUEPRINTS / "live-uav/send_mavlink.py")],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.perf_counter()
    try:
        _, error = command(cmd, timeout_s, env)
    finally:
        if sender is not None:
            sender.terminate()
    row: dict = {"ok": error is None, "error": error, "wall_s": round(time.perf_counter() - t0, 2),
                 "steps": 0, "tp_tv": None, "gpu_util_pct": None, "gpu_mem_mib": None}
    run = RunDir(out)
    if run.exists():
        status = run.status()
        row["steps"] = status.get("steps_done", 0)
        row["tp_tv"] = None if status.get("rtf") is None else round(float(status["rtf"]), 3)
        if status.get("error") and row["error"] is None:
            row["error"] = status["error"].get("message")
        try:
            totals = run.module_totals()
            utils = [t["gpu_util_mean_pct"] for t in totals if t.get("gpu_util_mean_pct") is not None]
            mems = [t["gpu_mem_max_mib"] for t in totals if t.get("gpu_mem_max_mib") is not None]
            row["gpu_util_pct"] = round(max(utils), 1) if utils else None
            row["gpu_mem_mib"] = round(max(mems), 0) if mems else None
        except (OSError, ValueError):
            pass
    return row


def length(config: pathlib.Path, steps: int) -> list[str]:
    """The overrides that make a blueprint run ``steps`` steps: ``episode.steps``, or for one
    that gives a ``duration`` (the core refuses both), that many sampling intervals of it."""
    import tomllib

    episode = tomllib.loads(config.read_text()).get("episode", {})
    if "duration" in episode:
        return ["--set", f"episode.duration={steps * float(episode['ts'])}"]
    return ["--set", f"episode.steps={steps}"]


def solve_times(n_uav: int, samples: int = 1_000_000, warmup: int = 5, reps: int = 8) -> dict[str, float]:
    """One solve of ``n_uav`` receivers along the SAR route (the UAVs move 0.5 m between
    solves): ``cold_s``, the first solve of the process (tracing and kernel compilation, or
    loading them from the kernel cache, included), and ``warm_s``, the median of ``reps``
    solves after ``warmup`` more (the shoot cache recorded, every kernel shape seen)."""
    import numpy as np

    from caviar_plugins import DATA
    from caviar_plugins.mobility import Path, read_waypoints
    from caviar_plugins.radio import RadioConfig, RadioScene
    from caviar_plugins.rt.settings import with_raytracing

    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    radio = RadioScene(with_raytracing(RadioConfig, samples_per_src=samples, uav_mesh=False), seed=0)
    starts = np.linspace(0.0, 0.9 * route.length, n_uav)
    times = []
    for k in range(1 + warmup + reps):
        radio.place({f"u{i}": route.at(s + 0.5 * k) for i, s in enumerate(starts)})
        t0 = time.perf_counter()
        radio.solve()
        times.append(time.perf_counter() - t0)
    return {"cold_s": round(times[0], 4), "warm_s": round(statistics.median(times[1 + warmup:]), 4)}


REFERENCE = ROOT / "docs/results/sar-links-cpu.json"
"""The main job's links by place and its outcome from a CPU run (``--write-reference``)."""


def recorded(run_dir: pathlib.Path) -> dict:
    """What the main job's comparison needs from a SAR run: each step's UAV place and best
    beam pair (``[x, y, z, best_pair]``, from ``3D.mobility.positions`` and
    ``communications.link``), and the last ``mission.result``. Read with pyarrow (the lent
    GPU machine has no polars)."""
    import pyarrow.parquet as pq

    from caviar.rundir import RunDir

    table = pq.read_table([str(f) for f in RunDir(run_dir).table_files("messages")],
                          columns=["step", "topic", "text"])
    places: dict[int, list[float]] = {}
    pairs: dict[int, int] = {}
    result = None
    for step, topic, text in zip(*(table.column(c).to_pylist() for c in ("step", "topic", "text")), strict=True):
        if topic == "3D.mobility.positions" and text:
            p = json.loads(text)["position"]
            places[step] = [p["x"], p["y"], p["z"]]
        elif topic == "communications.link" and text:
            pairs[step] = json.loads(text)["best_pair"]
        elif topic == "mission.result" and text:
            result = json.loads(text)
    links = [[*places[k], pairs[k]] for k in sorted(pairs) if k in places]
    return {"links": links, "mission_result": result}


def agreement(reference: dict, run: dict, tolerance_m: float = 0.25) -> dict:
    """The issue's accuracy criterion: the same number rescued as the CPU run, a mission time
    within the spread of the CPU runs with other seeds (``mission_time_s_by_seed`` of the
    reference, written by ``--seed-spread``; without it, the reference's own time), and the same
    best pair in ≥ 95 % of links by place (each link against the reference's link nearest to
    where the UAV was, within ``tolerance_m``)."""
    import numpy as np
    from scipy.spatial import cKDTree

    ref, got = np.asarray(reference["links"], float), np.asarray(run["links"], float)
    if not len(ref) or not len(got):
        return {"links": len(got), "matched_by_place": 0, "same_best_pair": None, "same_rescued": None,
                "mission_time_in_cpu_spread": None, "ok": False}
    distance, nearest = cKDTree(ref[:, :3]).query(got[:, :3])
    close = distance <= tolerance_m
    same = float(np.mean(got[close, 3] == ref[nearest[close], 3])) if close.any() else None
    a, b = reference.get("mission_result") or {}, run.get("mission_result") or {}
    times = [*(reference.get("mission_time_s_by_seed") or {}).values(), a.get("mission_time_s")]
    times = [t for t in times if t is not None]
    rescued = None if not b else a.get("rescued") == b.get("rescued")
    within = None if not b or not times or b.get("mission_time_s") is None else \
        min(times) <= b["mission_time_s"] <= max(times)
    return {"links": len(got), "matched_by_place": int(close.sum()),
            "same_best_pair": None if same is None else round(same, 4), "same_rescued": rescued,
            "mission_time_in_cpu_spread": within,
            "cpu_mission_time_spread_s": [min(times), max(times)] if times else None,
            "mission_time_minus_cpu_s": None if not b or b.get("mission_time_s") is None
            or a.get("mission_time_s") is None else round(b["mission_time_s"] - a["mission_time_s"], 3),
            "ok": bool(rescued) and bool(within) and same is not None and same >= 0.95}


KERNEL_CACHES = {
    "DRJIT_CACHE_DIR": ".drjit",  # Dr.Jit's compiled kernels (LLVM and CUDA); default ~/.drjit
    "OPTIX_CACHE_PATH": "optix",  # OptiX's ray-tracing pipelines; default /var/tmp/OptixCache_$USER
    "CUDA_CACHE_PATH": ".nv/ComputeCache",  # the CUDA driver's PTX -> SASS; default ~/.nv/ComputeCache
    "TORCHINDUCTOR_CACHE_DIR": "torchinductor",  # torch.compile's; default /tmp/torchinductor_$USER
    "TRITON_CACHE_DIR": ".triton/cache",  # Triton's GPU kernels; default ~/.triton/cache
}
"""Where compiled kernels are kept between runs (environment variable: folder under a root,
and the default). A user keeps them by keeping those folders (or pointing the variables at a
lasting disk): a second run then loads its kernels instead of compiling them."""


def kernel_caches(root: pathlib.Path) -> dict[str, str]:
    """The environment that puts every kernel cache of :data:`KERNEL_CACHES` under ``root``."""
    return {var: str(root / sub) for var, sub in KERNEL_CACHES.items()}


def main_job(timeout_s: float, work: pathlib.Path, sets: tuple[str, ...] = (),
             env: dict[str, str] | None = None) -> dict:
    """The SAR blueprint to its end: wall time from the command's start, T_p/T_v, outcome,
    and its links and outcome against the CPU reference (:data:`REFERENCE`)."""
    out = work / "main-job"
    row = run_blueprint("main-job", BLUEPRINTS / "sar/config.toml", sets, None, work, timeout_s, env)
    if row["steps"]:
        try:
            row["recorded"] = recorded(out)
            row["mission_result"] = row["recorded"]["mission_result"]
            if REFERENCE.exists():
                row["against_cpu"] = agreement(json.loads(REFERENCE.read_text()), row["recorded"])
        except (OSError, ValueError) as e:
            row["recorded_error"] = str(e)
    return row


def seed_spread(seeds: list[int]) -> int:
    """Runs the main job here with each of ``seeds`` (one Dr.Jit thread, as the reference) and
    writes their mission times into :data:`REFERENCE` (``mission_time_s_by_seed``, with the
    number each rescued): the spread a run elsewhere is held to."""
    reference = json.loads(REFERENCE.read_text())
    by_seed = dict(reference.get("mission_time_s_by_seed") or {})
    rescued = dict(reference.get("rescued_by_seed") or {})
    for seed in seeds:
        with tempfile.TemporaryDirectory(prefix="caviar-gpu-check-") as tmp:
            job = main_job(3600.0, pathlib.Path(tmp), ("modules.comm.params.raytracing.threads=1",
                                                       f"episode.seed={seed}"))
        if job["error"] is not None or not job.get("mission_result"):
            print(f"seed {seed}: the main job failed: {job['error']}")
            return 1
        by_seed[str(seed)] = job["mission_result"]["mission_time_s"]
        rescued[str(seed)] = job["mission_result"]["rescued"]
        print(f"seed {seed}: mission time {by_seed[str(seed)]} s, rescued {rescued[str(seed)]}", flush=True)
        reference.update(mission_time_s_by_seed=by_seed, rescued_by_seed=rescued)
        REFERENCE.write_text(json.dumps(reference) + "\n")
    return 0


NETWORK_GROUPS_PER_CALL = 25
"""The network items' groups of slots a compiled call (``groups_per_call``): a 0.1 s step's 25
groups in one call (a loop compiled once), each call's fixed host cost (dynamo's lookup, the
region's inputs) paid once a step, not 25 times (``benches/bench_host_overhead.py``)."""


def _network_command(n_ue: int, seconds: float) -> list[str]:
    """``benches/bench_network.py`` running the plugin alone at 21 cells × ``n_ue`` UEs, its UE
    reports one table a step."""
    return [sys.executable, str(ROOT / "benches/bench_network.py"), "--plugin-only", str(n_ue),
            "--seconds", str(seconds), "--ue-reports", "table"]


def network_graphed(n_ue: int, seconds: float, timeout_s: float) -> dict:
    """The same plugin with each compiled group of slots replayed as a CUDA graph (``cuda_graphs``,
    the default on CUDA since 2026-11-29, one group a call: :func:`network`'s chunks are loops, no
    graphs): the H200 (2026-11-28) found Sionna's OLLA reading a replay's overwritten output, now
    copied out: whether the graphs run without falling back (the run's stderr says where they do),
    and their T_p/T_v against :func:`network`'s."""
    stdout, error = command([*_network_command(n_ue, seconds), "--cuda-graphs"], timeout_s)
    return {"error": error} if error is not None else json.loads(stdout.strip().splitlines()[-1])


def network(n_ue: int, seconds: float, timeout_s: float) -> dict:
    """The radio network plugin at 21 cells × ``n_ue`` UEs for ``seconds`` of virtual time,
    its link levels through ``torch.compile`` as the blueprints have them, with
    :data:`NETWORK_GROUPS_PER_CALL` groups of slots a call; where that run fails (no Triton for
    the GPU, say), again without (one group a call: eager), with the compiled run's error kept."""
    cmd = _network_command(n_ue, seconds)
    stdout, compile_error = command([*cmd, "--groups-per-call", str(NETWORK_GROUPS_PER_CALL)], timeout_s)
    if compile_error is None:
        return {**json.loads(stdout.strip().splitlines()[-1]), "compile_error": None}
    if compile_error.startswith("timed out"):  # (slow, not broken: no second try)
        return {"error": compile_error, "compile_error": None}
    stdout, error = command([*cmd, "--eager"], timeout_s)
    if error is not None:
        return {"error": error, "compile_error": compile_error}
    return {**json.loads(stdout.strip().splitlines()[-1]), "compile_error": compile_error}


def check_blueprints(steps: int, only: list[str] | None, timeout_s: float) -> dict[str, dict]:
    """Every blueprint (``only`` these) for ``steps`` steps: the table's rows, printed as they come."""
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="caviar-gpu-check-") as tmp:
        for name, (config, sets, needs) in blueprint_runs(steps).items():
            if only and name not in only:
                continue
            why = missing(needs)
            sumo, recorded_run = sumo_module(config), TRAFFIC_RUNS / name
            replayed = None
            if why is not None and "libsumo" in why and sumo is not None and recorded_run.is_dir():
                config = replayed = replaying_traffic(config, *sumo, recorded_run)
                why = missing([m for m in needs if m != "libsumo"])
            if why is not None:
                rows[name] = {"ok": False, "error": f"skipped: {why}", "steps": 0, "tp_tv": None,
                              "gpu_util_pct": None, "gpu_mem_mib": None}
            else:
                try:
                    rows[name] = run_blueprint(name, config, sets, steps, pathlib.Path(tmp), timeout_s)
                finally:
                    if replayed is not None:
                        replayed.unlink()
                if replayed is not None:
                    rows[name]["traffic"] = "replayed from a recorded SUMO run (SUMO is not installed here)"
            r = rows[name]
            print(f"{name:14s} {r['steps']:>3} steps  {'ok' if r['ok'] else 'FAIL':4s}  "
                  f"T_p/T_v {r['tp_tv'] if r['tp_tv'] is not None else '-'}  GPU {r['gpu_util_pct']} %  "
                  f"{r['gpu_mem_mib']} MiB  {r['error'] or ''}{r.get('traffic', '')}", flush=True)
    return rows


def timings(result: dict, item_timeout_s: float, network_seconds: float, main_job_too: bool) -> None:
    """The timing items, into ``result``, printed as they come."""
    for key, n in (("solve_1uav_1e6", 1), ("solve_10uav_1e6", 10)):
        try:
            times = solve_times(n)
            result[f"{key}_cold_s"], result[f"{key}_warm_s"] = times["cold_s"], times["warm_s"]
        except Exception as e:  # noqa: BLE001 - reported, not fatal: the table matters more
            result[f"{key}_cold_s"] = result[f"{key}_warm_s"] = None
            result[f"{key}_error"] = str(e)
        print(f"{key}: cold {result[f'{key}_cold_s']} s, warm {result[f'{key}_warm_s']} s", flush=True)
    if main_job_too:  # twice: with empty kernel caches (cold), then with what the first run left (warm)
        with tempfile.TemporaryDirectory(prefix="caviar-gpu-check-") as tmp:
            env = kernel_caches(pathlib.Path(tmp) / "caches")
            for label in ("cold", "warm"):
                job = main_job(item_timeout_s, pathlib.Path(tmp) / label, env=env)
                job.pop("recorded", None)  # (thousands of rows: the comparison is what counts)
                result[f"main_job_{label}"] = job
                result[f"main_job_{label}_wall_s"] = job["wall_s"] if job["error"] is None else None
                print(f"main job ({label} kernel caches): {job}", flush=True)
        result["main_job_wall_s"] = result["main_job_cold_wall_s"]
    try:
        result["yolo"] = yolo_times()
    except Exception as e:  # noqa: BLE001 - reported, not fatal
        result["yolo"] = {"error": f"{type(e).__name__}: {e}"}
    print(f"yolo: {result['yolo']}", flush=True)
    try:
        result["pixel_forest"] = forest_times()
    except Exception as e:  # noqa: BLE001 - reported, not fatal
        result["pixel_forest"] = {"error": f"{type(e).__name__}: {e}"}
    print(f"pixel forest: {result['pixel_forest']}", flush=True)
    try:
        result["fit_scene"] = fit_times()
    except Exception as e:  # noqa: BLE001 - reported, not fatal
        result["fit_scene"] = {"error": f"{type(e).__name__}: {e}"}
    print(f"fit-scene: {result['fit_scene']}", flush=True)
    for n in (100, 1000):
        net = network(n, network_seconds, item_timeout_s)
        result[f"network_21x{n}"] = net
        result[f"network_21x{n}_tp_tv"] = net.get("tp_tv")
        print(f"network 21x{n}: T_p/T_v {net.get('tp_tv')} (first step {net.get('first_step_s')} s) "
              f"{net.get('error') or ''}", flush=True)
    graphed = network_graphed(100, network_seconds, item_timeout_s)
    result["network_21x100_cuda_graphs"] = graphed
    print(f"network 21x100, CUDA graphs: T_p/T_v {graphed.get('tp_tv')} {graphed.get('error') or ''}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=6, help="steps each blueprint runs")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds a blueprint may take")
    ap.add_argument("--out", type=pathlib.Path, default=ROOT / "docs/results/gpu.json")
    ap.add_argument("--no-timings", action="store_true", help="blueprints only")
    ap.add_argument("--only", nargs="*", help="these blueprints only")
    ap.add_argument("--item-timeout", type=float, default=150.0, help="seconds a timing item may take")
    ap.add_argument("--network-seconds", type=float, default=2.0,
                    help="virtual seconds of each network item (its first step not counted)")
    ap.add_argument("--no-main-job", action="store_true", help="without the main job (a CPU check)")
    ap.add_argument("--record-traffic", action="store_true",
                    help=f"record the SUMO blueprints' first steps to {TRAFFIC_RUNS.relative_to(ROOT)} "
                         "(where SUMO is installed), for machines without it; then stop")
    ap.add_argument("--seed-spread", type=int, nargs="*", metavar="SEED",
                    help=f"run the main job here with these seeds and add their mission times to "
                         f"{REFERENCE.relative_to(ROOT)} (the spread a GPU run is held to), then stop")
    ap.add_argument("--write-reference", action="store_true",
                    help=f"run the main job here and write its links and outcome to {REFERENCE.relative_to(ROOT)} "
                         "(on the CPU, with one Dr.Jit thread), then stop")
    args = ap.parse_args()
    dev = device()
    if args.record_traffic:
        return record_traffic()
    if args.seed_spread:
        return seed_spread(args.seed_spread)
    if args.write_reference:
        with tempfile.TemporaryDirectory(prefix="caviar-gpu-check-") as tmp:
            job = main_job(3600.0, pathlib.Path(tmp), ("modules.comm.params.raytracing.threads=1",))
        if job["error"] is not None:
            print(f"main job failed: {job['error']}")
            return 1
        REFERENCE.write_text(json.dumps({"device": dev["name"], "config": "blueprints/sar/config.toml",
                                         "set": ["modules.comm.params.raytracing.threads=1"],
                                         **job["recorded"]}) + "\n")
        print(f"wrote {REFERENCE}: {len(job['recorded']['links'])} links, {job['mission_result']}")
        return 0
    print(f"device: {dev['name']}; Dr.Jit variant {dev['drjit_variant']}; torch device {dev['torch_device']}",
          flush=True)
    rows = check_blueprints(args.steps, args.only, args.timeout)
    result: dict = {"device": dev["name"], "machine": dev, "steps_per_blueprint": args.steps,
                    "blueprints": {k: {"ok": v["ok"], "tp_tv": v["tp_tv"], "error": v["error"], "steps": v["steps"],
                                       "gpu_util_pct": v["gpu_util_pct"], "gpu_mem_mib": v["gpu_mem_mib"],
                                       **({"traffic": v["traffic"]} if "traffic" in v else {})}
                                   for k, v in rows.items()},
                    "main_job_wall_s": None, "network_21x100_tp_tv": None, "network_21x1000_tp_tv": None}
    if not args.no_timings:
        timings(result, args.item_timeout, args.network_seconds, main_job_too=not args.no_main_job)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0 if all(r["ok"] or str(r["error"]).startswith("skipped") for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
