"""The notebooks under examples/notebooks/ run from top to bottom, so they never rot.

Each is executed by nbclient in a real Jupyter kernel (ipykernel's ``python3``, which Jupyter
starts with the interpreter running the tests: .venv's python) in a temporary working
directory, so nothing is written into the checkout, with a time limit per cell and per
notebook. A failing cell fails the test with the notebook's name, the cell's source and its
traceback. Notebooks are committed without outputs.
"""

from __future__ import annotations

import pathlib
import re
import sys
import time

import nbformat
import pytest
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError, CellTimeoutError

ROOT = pathlib.Path(__file__).resolve().parent.parent
NOTEBOOK_DIR = ROOT / "examples" / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
CELL_TIMEOUT_S = 120
NOTEBOOK_TIMEOUT_S = 240
KERNEL_CHECK = "import sys\nprint(sys.executable)"
PLOTS = ("plt.show()", "display(Image(")
"""Cells with one of these show an image."""


def execute(path: pathlib.Path, workdir: pathlib.Path) -> nbformat.NotebookNode:
    """Runs the notebook at ``path`` with ``workdir`` as the kernel's working directory,
    after a first cell (added to the copy that runs) that prints the kernel's interpreter;
    returns the notebook with its outputs."""
    nb = nbformat.read(path, as_version=4)
    nb.cells.insert(0, nbformat.v4.new_code_cell(KERNEL_CHECK))
    deadline = time.monotonic() + NOTEBOOK_TIMEOUT_S

    def cell_timeout(cell: nbformat.NotebookNode) -> int:
        """A cell's limit: its own, or what is left of the notebook's (nbclient stops the cell)."""
        return max(1, min(CELL_TIMEOUT_S, int(deadline - time.monotonic())))

    client = NotebookClient(nb, kernel_name="python3", timeout_func=cell_timeout,
                            resources={"metadata": {"path": str(workdir)}})
    try:
        client.execute()
    except CellTimeoutError as e:
        pytest.fail(f"{path.name}: a cell ran past its limit ({CELL_TIMEOUT_S} s per cell, "
                    f"{NOTEBOOK_TIMEOUT_S} s per notebook)\n{e}", pytrace=False)
    except CellExecutionError as e:
        plain = re.sub(r"\x1b\[[0-9;]*m", "", str(e))  # the traceback without its terminal colours
        pytest.fail(f"{path.name}: a cell failed\n{plain}", pytrace=False)
    return nb


def stdout_of(cell: nbformat.NotebookNode) -> str:
    return "".join(o.get("text", "") for o in cell.outputs if o.get("output_type") == "stream")


def test_notebooks_are_found():
    names = [p.name for p in NOTEBOOKS]
    assert "01-first-run.ipynb" in names and "02-writing-a-plugin.ipynb" in names, names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [i for i, c in enumerate(nb.cells)
             if c.cell_type == "code" and (c.outputs or c.execution_count is not None)]
    assert not dirty, f"{path.name}: cells {dirty} have outputs; clear them before committing"


def left_in_checkout() -> list[pathlib.Path]:
    """What a notebook could leave in the checkout: run directories, files beside the notebooks."""
    runs = [p for d in ("blueprints", "examples") for p in (ROOT / d).rglob("runs") if p.is_dir()]
    beside = [p for p in NOTEBOOK_DIR.iterdir() if p.suffix != ".ipynb"]
    return sorted(runs + beside)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    before = left_in_checkout()
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the kernel's temporary folders too
    nb = execute(path, tmp_path)
    kernel_python = stdout_of(nb.cells[0]).strip()
    assert pathlib.Path(kernel_python) == pathlib.Path(sys.executable), (
        f"the kernel ran {kernel_python!r}, not this interpreter {sys.executable!r}")
    # A plot that silently stopped showing (a module switched matplotlib's backend, say) is rot too.
    blank = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and any(s in c.source for s in PLOTS)
             and not any("image/png" in o.get("data", {}) for o in c.outputs)]
    assert not blank, f"{path.name}: cells {blank} (counting the added first cell) show no image"
    assert left_in_checkout() == before, f"{path.name} wrote into the checkout"


def write_notebook(path: pathlib.Path, *sources: str) -> pathlib.Path:
    nbformat.write(nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(s) for s in sources]), path)
    return path


def test_a_failing_cell_fails_the_test_with_its_source_and_error(tmp_path):
    nb = write_notebook(tmp_path / "broken.ipynb", "x = 1", "y = x / 0")
    with pytest.raises(pytest.fail.Exception) as failed:
        execute(nb, tmp_path)
    message = str(failed.value)
    assert "broken.ipynb: a cell failed" in message
    assert "y = x / 0" in message and "ZeroDivisionError: division by zero" in message
    assert "\x1b[" not in message


def test_a_notebook_past_its_time_limit_is_stopped(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "NOTEBOOK_TIMEOUT_S", 3)
    nb = write_notebook(tmp_path / "slow.ipynb", "import time", "time.sleep(60)")
    start = time.monotonic()
    with pytest.raises(pytest.fail.Exception) as failed:
        execute(nb, tmp_path)
    assert time.monotonic() - start < 30
    message = str(failed.value)
    assert "slow.ipynb: a cell ran past its limit" in message and "3 s per notebook" in message
    assert "time.sleep(60)" in message
