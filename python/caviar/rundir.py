"""A run directory, read: the one reader behind :func:`caviar.load_run`, ``caviar-core
report`` and the browser view.

Where things are is the core's knowledge, not this module's: the files holding a table
come from :func:`caviar._core.table_files` (the compacted ``messages.parquet``, or the
parts of a run in progress or killed), the status from :func:`caviar._core.run_status`
(with what a reader concludes about a run left running) and the per-module totals from
:func:`caviar._core.module_totals` (what ``caviar-core inspect`` prints).
"""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any, Sequence

from caviar import _core

TABLES = ("messages", "timings")


class RunDir:
    """A run directory: its status, configuration and recorded tables."""

    def __init__(self, path: str | os.PathLike):
        self.path = pathlib.Path(path)

    def exists(self) -> bool:
        """Whether it has a run.json (a run was started in it)."""
        return (self.path / "run.json").is_file()

    def status(self) -> dict[str, Any]:
        """run.json, as :class:`caviar.RunStatus` describes it."""
        if not self.exists():
            raise FileNotFoundError(f"{self.path}: not a run directory (no run.json)")
        return json.loads(_core.run_status(self.path))

    def config_text(self) -> str:
        path = self.path / "config.toml"
        try:
            return path.read_text()
        except UnicodeDecodeError as e:
            raise ValueError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None

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
        return len(files) == 1 and files[0].name == f"{table}.parquet"

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
