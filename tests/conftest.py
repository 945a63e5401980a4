import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"
sys.path.insert(0, str(TESTS))  # test plugins live in tests/sample_plugins.py

import view_support  # noqa: E402  (the view tests' helpers, on the path just set)


def write_config(tmp_path: pathlib.Path, text: str, name: str = "exp.toml") -> pathlib.Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture
def cli(tmp_path):
    """Runs the installed `caviar-core` console script in tmp_path."""

    def run(*args, check=None):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
        exe = pathlib.Path(sys.executable).parent / "caviar-core"
        p = subprocess.run([str(exe), *map(str, args)], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=300)
        if check is not None:
            assert p.returncode == check, f"exit {p.returncode}\nstdout:\n{p.stdout}\nstderr:\n{p.stderr}"
        return p

    return run


# --- the browser view's (tests/test_view.py, tests/test_view_serving.py; helpers in view_support.py)

@pytest.fixture(scope="module")
def qs_run(tmp_path_factory):
    """The quickstart, recorded (1,525 steps, one UAV)."""
    out = tmp_path_factory.mktemp("view") / "qs"
    p = view_support.run_caviar("run", ROOT / "blueprints/quickstart/config.toml", "--out", out, "-q",
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log
    return out


@pytest.fixture(scope="module")
def positions(qs_run):
    import json

    import polars as pl

    m = pl.read_parquet(qs_run / "messages.parquet")
    m = m.filter(pl.col("topic") == "3D.mobility.positions")
    payloads = map(json.loads, m["text"].to_list())
    return {(s, d["UE_Id"]): d["position"] for s, d in zip(m["step"].to_list(), payloads, strict=True)}


@pytest.fixture(scope="module")
def server(qs_run):
    from caviar.view import start_server

    srv = start_server(qs_run, pending=False)
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    if not pathlib.Path(view_support.CHROMIUM).exists():
        pytest.skip(f"{view_support.CHROMIUM} missing (apt-get install chromium)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=view_support.CHROMIUM, args=view_support.CHROMIUM_ARGS)
        yield b
        b.close()
