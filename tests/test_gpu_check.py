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
