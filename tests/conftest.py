import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"
sys.path.insert(0, str(TESTS))  # test plugins live in tests/sample_plugins.py


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
