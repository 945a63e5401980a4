"""``scripts/gpu_check.py`` (issue #39, part 2), on whatever machine runs the tests: it knows
every blueprint, runs one for a few steps, and writes gpu.json with the keys the issue names
(the timing items left out here: they take minutes; a GPU session runs them)."""

import json
import subprocess
import sys

from conftest import ROOT

sys.path.insert(0, str(ROOT / "scripts"))
import gpu_check  # noqa: E402


def test_the_check_knows_every_blueprint():
    listed = set(gpu_check.blueprint_runs(3))
    folders = {p.parent.name for p in (ROOT / "blueprints").glob("*/config.toml")}
    assert folders - listed == {"legacy"}, "a blueprint the GPU check does not run (or name why it does not)"
    for name, (config, _, _) in gpu_check.blueprint_runs(3).items():
        assert config.is_file(), name


def test_a_short_check_writes_gpu_json_with_the_issues_keys(tmp_path):
    out = tmp_path / "gpu.json"
    p = subprocess.run([sys.executable, str(ROOT / "scripts/gpu_check.py"), "--only", "quickstart", "--steps", "2",
                        "--no-timings", "--out", str(out)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "quickstart" in p.stdout and "ok" in p.stdout
    result = json.loads(out.read_text())
    for key in ("device", "main_job_wall_s", "network_21x100_tp_tv", "network_21x1000_tp_tv", "blueprints"):
        assert key in result, key
    row = result["blueprints"]["quickstart"]
    assert row["ok"] is True and row["error"] is None and row["steps"] == 2 and row["tp_tv"] > 0
    assert result["device"] == result["machine"]["name"]


def test_the_comparison_by_place_counts_equal_best_pairs_at_the_nearest_place():
    reference = {"links": [[0.0, 0.0, 10.0, 5], [10.0, 0.0, 10.0, 7], [20.0, 0.0, 10.0, 9]],
                 "mission_result": {"rescued": 6, "mission_time_s": 100.0},
                 "mission_time_s_by_seed": {"2": 97.5, "3": 104.0}}
    run = {"links": [[0.1, 0.0, 10.0, 5], [10.0, 0.1, 10.0, 7], [19.9, 0.0, 10.0, 8], [50.0, 0.0, 10.0, 1]],
           "mission_result": {"rescued": 6, "mission_time_s": 102.0}}
    a = gpu_check.agreement(reference, run)
    assert a == {"links": 4, "matched_by_place": 3, "same_best_pair": round(2 / 3, 4), "same_rescued": True,
                 "mission_time_in_cpu_spread": True, "cpu_mission_time_spread_s": [97.5, 104.0],
                 "mission_time_minus_cpu_s": 2.0, "ok": False}  # (a place 30 m from any reference one: not compared)
    run["links"][2][3] = 9
    assert gpu_check.agreement(reference, run)["ok"] is True
    run["mission_result"]["mission_time_s"] = 104.5  # (outside what the CPU gave with any seed)
    assert gpu_check.agreement(reference, run)["mission_time_in_cpu_spread"] is False
    assert gpu_check.agreement(reference, run)["ok"] is False
    run["mission_result"].update(mission_time_s=100.0, rescued=5)
    assert gpu_check.agreement(reference, run)["same_rescued"] is False
    del reference["mission_time_s_by_seed"]  # (no spread measured: the reference's own time only)
    assert gpu_check.agreement(reference, run)["cpu_mission_time_spread_s"] == [100.0, 100.0]


def test_kernel_caches_all_go_under_one_root(tmp_path):
    env = gpu_check.kernel_caches(tmp_path)
    assert set(env) == {"DRJIT_CACHE_DIR", "OPTIX_CACHE_PATH", "CUDA_CACHE_PATH", "TORCHINDUCTOR_CACHE_DIR",
                        "TRITON_CACHE_DIR"}
    assert all(v.startswith(str(tmp_path)) for v in env.values())


def test_the_machine_is_named_as_it_is():
    """The bench helper once said "no GPU ... Dr.Jit LLVM" on an H200: it now reads each part."""
    import torch

    sys.path.insert(0, str(ROOT / "benches"))
    from bench_common import machine
    from caviar_plugins.machine import describe

    d = describe()
    assert (d["gpu"] is None) == (not torch.cuda.is_available())
    assert d["drjit_variant"].startswith(("llvm_", "cuda_")) and d["torch_device"]
    line = machine()
    assert d["processor"] in line and d["drjit_variant"] in line and f"torch device {d['torch_device']}" in line
    assert ("no GPU" in line) == (d["gpu"] is None)


def test_a_cpu_run_of_the_main_job_agrees_with_the_reference_by_place(tmp_path):
    """The first 20 steps of the main job on this machine against the committed CPU run's
    links (``--write-reference``): the same best pair at ≥ 95 % of the places, the GPU run's
    criterion."""
    reference = json.loads(gpu_check.REFERENCE.read_text())
    assert len(reference["links"]) > 2000 and reference["mission_result"]["rescued"] == 6
    job = gpu_check.main_job(600, tmp_path, ("episode.steps=20", "modules.comm.params.raytracing.threads=1"))
    assert job["error"] is None, job["error"]
    against = job["against_cpu"]
    assert against["links"] == 20 and against["matched_by_place"] == 20, against
    assert against["same_best_pair"] >= 0.95, against


def test_a_sumo_blueprint_runs_on_its_recorded_traffic_where_sumo_is_missing(tmp_path):
    """SUMO cannot travel to the lent GPU machine: there the check replays the traffic
    recorded here (``--record-traffic``) with ``caviar.replay`` in place of the ``sumo-traffic``
    module, and the rest of the blueprint runs as it is."""
    import pyarrow.parquet as pq

    config = ROOT / "blueprints/osm-traffic/config.toml"
    name, stage = gpu_check.sumo_module(config)
    recorded = gpu_check.TRAFFIC_RUNS / "osm-traffic"
    variant = gpu_check.replaying_traffic(config, name, stage, recorded)
    try:
        assert "sumo-traffic" not in variant.read_text() and "caviar.replay" in variant.read_text()
        row = gpu_check.run_blueprint("osm-traffic", variant, [], 3, tmp_path, 300)
    finally:
        variant.unlink()
    assert row["ok"] and row["steps"] == 3, row
    def positions(run):
        t = pq.read_table(str(run / "messages.parquet"), columns=["step", "source", "topic", "text"]).to_pylist()
        return [(m["step"], m["topic"], m["text"]) for m in t if m["source"] == name and m["step"] < 3]
    replayed, original = positions(tmp_path / "osm-traffic"), positions(recorded)
    assert replayed and replayed == original  # the recorded vehicles, step by step
