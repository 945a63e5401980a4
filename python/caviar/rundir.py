"""A run directory, read: the one Python reader of what the core writes, behind
:func:`caviar.load_run`, ``caviar-core report``, the browser view, the supervisor of
``caviar-core run`` and the SAR results. No other Python module names the core's files
(``tests/test_rundir.py`` checks it).

Where things are is the core's knowledge, not this module's: the files holding a table
come from :func:`caviar._core.table_files` (the compacted ``messages.parquet``, or the
parts of a run in progress or killed), the status from :func:`caviar._core.run_status`
(with what a reader concludes about a run left running), the per-module totals from
:func:`caviar._core.module_totals` (what ``caviar-core inspect`` prints), and closing a run
whose process died from :func:`caviar._core.close_failed_run`.
"""

from __future__ import annotations

import json
import os
import pathlib
import sys
from typing import Any, Sequence

from caviar import _core

TABLES = ("messages", "timings")
FILES = _core.run_dir_files()
"""The names of a run directory's files, from the core that writes them (``status``:
run.json, ``progress``, ``config``, ``checkpoint``)."""
STATUS_FILE = FILES["status"]
CONFIG_FILE = FILES["config"]


class RunDir:
    """A run directory: its status, configuration and recorded tables."""

    def __init__(self, path: str | os.PathLike):
        self.path = pathlib.Path(path)

    def exists(self) -> bool:
        """Whether it has a run.json (a run was started in it)."""
        return (self.path / STATUS_FILE).is_file()

    def require(self, hint: str = "") -> None:
        """FileNotFoundError naming the directory unless a run was started in it; ``hint``
        follows (what to give instead)."""
        if not self.exists():
            raise FileNotFoundError(f"{self.path}: not a run directory (no {STATUS_FILE}){hint}")

    def status(self) -> dict[str, Any]:
        """run.json, as :class:`caviar.RunStatus` describes it."""
        self.require()
        return json.loads(_core.run_status(self.path))

    def status_stamp(self) -> int | None:
        """When run.json last changed (ns; None: there is none): a poller reads the status
        again only when this moves."""
        try:
            return (self.path / STATUS_FILE).stat().st_mtime_ns
        except OSError:
            return None

    def completed(self) -> bool:
        """Whether the run in it finished as planned (status ``completed``)."""
        try:
            return self.status().get("status") == "completed"
        except (OSError, ValueError):
            return False

    @property
    def config_file(self) -> pathlib.Path:
        """The configuration the run ran, as the core copied it (``--set`` applied)."""
        return self.path / CONFIG_FILE

    def config_text(self) -> str:
        path = self.config_file
        try:
            return path.read_text()
        except UnicodeDecodeError as e:
            raise ValueError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None

    def config(self) -> dict[str, Any]:
        """The configuration, parsed ({} before the core wrote it); ValueError naming the
        file when it cannot be read."""
        if not self.config_file.is_file():
            return {}
        if sys.version_info >= (3, 11):
            import tomllib
        else:  # pragma: no cover (tomli: the `ml` extra; only a reader of the config needs it)
            import tomli as tomllib
        try:
            return tomllib.loads(self.config_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{self.config_file}: unreadable config ({e})") from None

    def close_failed(self, message: str) -> str | None:
        """Closes a run whose process died while it was ``running`` as ``failed`` with
        ``message`` and where it was (the module and step ``progress.json`` names), as the
        core does (:func:`caviar._core.close_failed_run`); that place in words, or None when
        the run was not running."""
        return _core.close_failed_run(self.path, message)

    def table_files(self, table: str) -> list[pathlib.Path]:
        """The Parquet files of ``table`` in order; FileNotFoundError when the run has
        no such table (yet)."""
        try:
            return [pathlib.Path(p) for p in _core.table_files(self.path, table)]
        except ValueError as e:
            raise FileNotFoundError(str(e)) from None

    def is_compacted(self, table: str, files: Sequence[pathlib.Path] | None = None) -> bool:
        """Whether ``table`` is one compacted file (a run that finished), not parts (a run
        in progress or killed, read part by part as they come). ``files``: the table's
        files as :meth:`table_files` just listed them (default: listed now)."""
        files = self.table_files(table) if files is None else files
        return len(files) == 1 and files[0].name == _core.compacted_file(table)

    def read(self, table: str, columns: Sequence[str] | None = None,
             files: Sequence[pathlib.Path] | None = None):
        """``table`` (or only ``files`` of it) as one polars DataFrame; an empty one for a
        run that failed before its first step."""
        import polars as pl

        frames = [read_parquet(f, columns) for f in (self.table_files(table) if files is None else files)]
        if frames:
            return pl.concat(frames)
        schema = _schema(table)
        return pl.DataFrame(schema={c: t for c, t in schema.items() if columns is None or c in columns})

    def module_totals(self) -> list[dict[str, Any]]:
        """Per module, its timings added up (the core's row last)."""
        try:
            return json.loads(_core.module_totals(self.path))
        except ValueError as e:
            raise FileNotFoundError(str(e)) from None


def _schema(table: str) -> dict[str, Any]:
    """The columns of a recorded table (as the core's recorder writes them), for the
    empty frame of a run that recorded nothing."""
    import polars as pl

    if table == "messages":
        return {"step": pl.UInt64, "time": pl.Float64, "seq": pl.UInt32, "source": pl.String,
                "topic": pl.String, "kind": pl.String, "text": pl.String, "meta": pl.String,
                "data": pl.Binary}
    return {"step": pl.UInt64, "time": pl.Float64, "module": pl.String, "wall_s": pl.Float64,
            "cpu_s": pl.Float64, "rss_mib": pl.Float64, "msgs_in": pl.UInt32, "msgs_out": pl.UInt32,
            "gpu_util_pct": pl.Float64, "gpu_mem_mib": pl.Float64}


def read_parquet(path: pathlib.Path, columns: Sequence[str] | None = None):
    """One Parquet file; ValueError naming it when it cannot be read."""
    import polars as pl

    try:
        return pl.read_parquet(path, columns=list(columns) if columns is not None else None)
    except Exception as e:  # polars raises several kinds for a damaged file
        raise ValueError(f"{path}: not a readable Parquet file ({str(e).splitlines()[0]})") from None
