"""What every plugin's ``figures(log, out)`` for ``caviar-core report`` (entry-point group
``caviar.report``) does around its own drawing: matplotlib without a display, the folder
to draw in, each figure laid out, saved and closed, and the numbers beside the figures.

    plt = pyplot_into(out)
    fig, ax = plt.subplots()
    ...
    return [save_figure(fig, out / "name.png"), save_numbers(summary, out / "name.json")]
"""

from __future__ import annotations

import json
import pathlib
from typing import Any


def pyplot_into(out: pathlib.Path) -> Any:
    """matplotlib's ``pyplot`` on the Agg backend (no display needed), with the folder ``out``
    made. matplotlib is imported here, only by a report that draws something."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    return plt


def save_figure(fig: Any, path: pathlib.Path) -> pathlib.Path:
    """Lays ``fig`` out, writes it to ``path`` at 100 dpi and closes it; returns ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def save_numbers(numbers: dict[str, Any], path: pathlib.Path, indent: int = 1) -> pathlib.Path:
    """Writes the numbers the figures show to ``path`` as JSON; returns ``path``."""
    path.write_text(json.dumps(numbers, indent=indent) + "\n")
    return path
