"""MkDocs hooks of the documentation site (mkdocs.yml ``hooks:``).

The results page lists every file of ``docs/results/`` as it is when the site is built.

Paths are checked: every repository path a page writes as code (``crates/…``,
``plugins/…``, ``tests/…``, …) must exist, or the strict build fails naming the page and
the path, so that the pages (the architecture page first) stay true to the code.

The tutorial notebooks stay where the tests run them (``examples/notebooks/``,
``tests/test_notebooks.py``); this hook adds them to the site as ``notebooks/NAME.ipynb``,
before mkdocs-jupyter turns them into pages (it converts them without running them: they
are committed without outputs), and puts a note on each saying so.
"""

from __future__ import annotations

import logging
import pathlib
import re

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

log = logging.getLogger("mkdocs.hooks.caviar")

ROOT = pathlib.Path(__file__).resolve().parent.parent
# A repository path written as code: `crates/caviar-core/src/engine.rs`, `blueprints/sar/`.
_PATH = re.compile(r"`((?:crates|python|plugins|tests|benches|blueprints|scripts|examples|docs|web)/[\w./-]*)`")
# Not checked: pages written by scripts, and the reading of the 2023 code, whose paths are that
# repository's (lasseufpa/caviar).
_UNCHECKED = ("results/", "reference/cli.md", "paper-era-code.md")
_PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*$|NNN")  # transport/KIND/, runs/NAME-NNN
EXAMPLES = ROOT / "examples"
NOTEBOOKS = EXAMPLES / "notebooks"

NOTE = (
    '<div class="admonition note"><p class="admonition-title">A notebook run by the tests</p>'
    "<p>This page is <code>examples/notebooks/{name}</code>, shown without its outputs: the test "
    "command runs every notebook from top to bottom (<code>tests/test_notebooks.py</code>), and "
    "each checks its own numbers with <code>assert</code>s. Open it with Jupyter to run it: "
    "<code>.venv/bin/pip install jupyterlab</code> and "
    "<code>.venv/bin/jupyter lab examples/notebooks</code>.</p></div>\n"
)


@event_priority(100)  # before mkdocs-jupyter's on_files, which makes pages of .ipynb files
def on_files(files: Files, config) -> Files:
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        uri = path.relative_to(EXAMPLES).as_posix()
        files.append(File(uri, src_dir=str(EXAMPLES), dest_dir=config["site_dir"],
                          use_directory_urls=config["use_directory_urls"]))
    return files


def results_files() -> str:
    """A table of every file in docs/results/, linked from measured/index.md."""
    rows = ["| file | size |", "|---|---:|"]
    results = ROOT / "docs" / "results"
    for path in sorted(p for p in results.rglob("*") if p.is_file()):
        rel = path.relative_to(results).as_posix()
        size = path.stat().st_size
        shown = f"{size / 1024:.1f} KiB" if size >= 1024 else f"{size} B"
        rows.append(f"| [`{rel}`](../results/{rel}) | {shown} |")
    return "\n".join(rows) + "\n"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri == "measured/index.md":
        markdown = markdown.replace("<!-- results-files -->", results_files())
    if not page.file.src_uri.startswith(_UNCHECKED):
        for path in sorted(set(_PATH.findall(markdown))):
            if any(_PLACEHOLDER.search(part) for part in path.split("/")):
                continue
            if not (ROOT / path).exists():
                log.warning("%s names `%s`, which does not exist in the repository", page.file.src_uri, path)
    return markdown


def on_page_content(html: str, page, config, files) -> str:
    if page.file.src_uri.startswith("notebooks/") and page.file.src_uri.endswith(".ipynb"):
        return NOTE.format(name=page.file.src_uri.split("/", 1)[1]) + html
    return html
