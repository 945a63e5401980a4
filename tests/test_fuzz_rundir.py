"""The Python run reader fuzzed with hypothesis (issue #28): real run directories (one
finished and compacted, one killed mid-run and left in parts) with a file corrupted byte
by byte, truncated, removed, or run.json given values of the wrong type. The reader
either reads the run or raises an error (ValueError or OSError) that names the run
directory; never another exception, never a hang.

Bounded and derandomized in the test command (CAVIAR_FUZZ_EXAMPLES examples per target,
150 by default); `scripts/fuzz.sh` runs more and records the counts
(CAVIAR_FUZZ_REPORT)."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess
import tempfile
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import caviar
from caviar.rundir import RunDir
from configs import caviar_core, caviar_env, episode, module, output

EXAMPLES = int(os.environ.get("CAVIAR_FUZZ_EXAMPLES", "150"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])
COUNTS: dict[str, int] = {}

def config(at: int) -> str:
    """12 steps, checkpoints every 4, the process ending at step ``at``."""
    return (episode(0.1, ["a", "b"], steps=12) + output(checkpoint_every=4)
            + module("count", "a", "sample_plugins:Counter") + module("noise", "a", "sample_plugins:Noise")
            + module("exiter", "b", "sample_plugins:Exits", {"at_step": at}))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[pathlib.Path]:
    """A finished run, and one whose process ended at step 6 (parts, run.json `running`)."""
    root = tmp_path_factory.mktemp("fuzz-runs")
    env = caviar_env(CAVIAR_SUPERVISED="1")  # unsupervised: nobody closes the killed run
    out = []
    for name, at in (("finished", 99), ("killed", 6)):
        (root / f"{name}.toml").write_text(config(at))
        subprocess.run([caviar_core(), "run", f"{name}.toml", "-q", "--out", name], cwd=root, env=env,
                       capture_output=True, timeout=120)
        out.append(root / name)
    assert caviar.load_run(out[0]).status["status"] == "completed"
    assert caviar.load_run(out[1]).status["status"] == "abandoned"
    return out


def _files(run: pathlib.Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file())


def _read_everything(run: pathlib.Path) -> None:
    """The reader's entry points; what they return is used, as a user would."""
    rd = RunDir(run)
    rd.status()
    rd.config_text()
    rd.module_totals()
    log = caviar.load_run(run)
    log.messages.height + log.timings.height  # noqa: B018 (read)
    log.topic("count")


def _check(run: pathlib.Path, target: str) -> None:
    COUNTS[target] = COUNTS.get(target, 0) + 1
    t0 = time.monotonic()
    try:
        _read_everything(run)
    except (ValueError, OSError) as e:
        assert str(run) in str(e), f"{type(e).__name__} does not name the run directory: {e}"
    assert time.monotonic() - t0 < 20, "the reader hung"


@st.composite
def byte_edits(draw, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        at = draw(st.integers(0, max(len(b) - 1, 0)))
        if op == "flip" and b:
            b[at] ^= draw(st.integers(1, 255))
        elif op == "insert":
            b.insert(at, draw(st.integers(0, 255)))
        elif op == "delete" and b:
            del b[at:at + draw(st.integers(1, 64))]
        elif op == "truncate":
            del b[at:]
    return bytes(b)


def _copy(run: pathlib.Path) -> pathlib.Path:
    scratch = pathlib.Path(tempfile.mkdtemp(prefix="caviar-fuzz-"))
    dst = scratch / run.name
    shutil.copytree(run, dst)
    return dst


def test_a_corrupt_file_is_reported_naming_the_run(runs):
    choices = [(run, f) for run in runs for f in _files(run)]

    @FUZZ
    @given(data=st.data(), which=st.sampled_from(choices), remove=st.booleans())
    def corrupt(data, which, remove):
        run, rel = which
        dst = _copy(run)
        try:
            target = dst / rel
            if remove and data.draw(st.integers(0, 9)) == 0:
                target.unlink()
            else:
                target.write_bytes(data.draw(byte_edits(target.read_bytes())))
            _check(dst, "python run reader: corrupt files")
        finally:
            shutil.rmtree(dst.parent)

    corrupt()


JSON_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True),
                        st.text(max_size=8), st.lists(st.integers(), max_size=3),
                        st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


def test_run_json_with_values_of_the_wrong_type_is_reported_naming_the_run(runs):
    @FUZZ
    @given(run=st.sampled_from(runs), edits=st.lists(st.tuples(st.sampled_from([
        "status", "steps_done", "steps_planned", "ts", "wall_s", "seed", "modules", "error", "pid",
        "pid_start", "end_reason", "pacing", "resumed_at", "checkpoint_step", "last_modules"]), JSON_VALUES),
        min_size=1, max_size=3), top=st.sampled_from(["object", "list", "scalar"]))
    def wrong_types(run, edits, top):
        dst = _copy(run)
        try:
            status = json.loads((dst / "run.json").read_text())
            for key, value in edits:
                status[key] = value
            doc = status if top == "object" else [status] if top == "list" else 3
            (dst / "run.json").write_text(json.dumps(doc))
            _check(dst, "python run reader: run.json types")
        finally:
            shutil.rmtree(dst.parent)

    wrong_types()


@pytest.fixture(scope="module", autouse=True)
def report():
    yield
    path = os.environ.get("CAVIAR_FUZZ_REPORT")
    if path:
        with open(path, "a") as f:
            for target, cases in COUNTS.items():
                f.write(json.dumps({"target": target, "cases": cases, "failures": 0}) + "\n")
