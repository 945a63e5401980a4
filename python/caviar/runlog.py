"""Reading a recorded run into polars (or pandas), through :class:`caviar.rundir.RunDir`."""

from __future__ import annotations

import json
import os
import typing
from typing import Literal, Optional, TypedDict

from caviar._core import RawMessage
from caviar.plugin import Message
from caviar.rundir import RunDir
from caviar.topics import matches


class RunErrorInfo(TypedDict, total=False):
    """``error`` in run.json: ``message`` always; where a module failed also ``module``,
    ``phase`` (setup, step, teardown), ``step``, ``time`` and ``trace``."""

    message: str
    module: str
    phase: str
    step: Optional[int]
    time: Optional[float]
    trace: Optional[str]


EndReason = Literal["steps", "module", "error", "interrupted", "closed"]
"""Why an episode ended: its planned steps ran, a module published
``caviar.episode.end``, an error, Ctrl-C, or the host closed it early."""


class _RunStatusFields(TypedDict):
    """The fields of run.json present in every run."""

    caviar_version: str
    status: Literal["running", "completed", "failed", "interrupted", "abandoned"]
    """``abandoned``: run.json said running but the process that ran it is gone."""
    config_file: str
    overrides: list[str]
    seed: int
    ts: float
    steps_planned: Optional[int]
    steps_done: int
    """Steps that finished: for a run that failed at step k (0-based), k, whatever the fault
    (an exception, an exit, a crash, a deadline; in process or over NATS)."""
    virtual_time_s: float
    wall_s: float
    record_s: float
    rtf: Optional[float]
    """The paper's RTF = T_p/T_v, wall-clock s per virtual s (runs without
    ``rtf_definition`` stored the inverse)."""
    modules: list[str]
    error: Optional[RunErrorInfo]


class RunStatus(_RunStatusFields, total=False):
    """run.json, as the core writes it (``caviar_core::status::RunStatus``)."""

    rtf_definition: str
    """What ``rtf`` means, in words (absent in runs that stored the inverse)."""
    end_reason: EndReason
    """Absent while running and in runs recorded before it was added."""
    ended_by: str
    """The module that published ``caviar.episode.end``, when that ended the episode."""
    pid: int
    """The process running the episode (while running)."""
    last_step: int
    """For a run left running: the step in progress when last seen, its stage and the
    modules that had started it (``last_stage``, ``last_modules``)."""
    last_stage: str
    last_modules: list[str]
    abandoned: str
    """For an abandoned run: how far it got and what it was doing, in words."""
    checkpoint_step: int
    """The step the last checkpoint resumes at (``caviar-core run --resume``)."""
    resumed_at: list[int]
    """The steps the run was resumed at, in order (absent: never resumed)."""
    checkpoint_s: float
    """Seconds of ``wall_s`` spent writing checkpoints (since the last resume)."""


class RunLog:
    """A recorded run: ``messages`` and ``timings`` as polars DataFrames.

    Works on finished runs and on runs that crashed or are still going.
    """

    def __init__(self, path: str | os.PathLike):
        self.run = RunDir(path)
        self.path = self.run.path
        self.status: RunStatus = typing.cast(RunStatus, self.run.status())
        self.messages = self.run.read("messages")
        self.timings = self.run.read("timings")

    @property
    def config_text(self) -> str:
        return self.run.config_text()

    def _select(self, pattern: str):
        import polars as pl

        matches(pattern, "x")  # ValueError for a pattern that is not valid, messages or not
        if self.messages.is_empty():
            return self.messages
        topics = [t for t in self.messages["topic"].unique().to_list() if matches(pattern, t)]
        return self.messages.filter(pl.col("topic").is_in(topics))

    def topic(self, pattern: str):
        """JSON messages on matching topics, one row each: step, time, topic, source and
        the payload's fields as columns (nested objects stay structs; a payload field
        named like one of the first four becomes ``payload.NAME``)."""
        import polars as pl

        rows = self._select(pattern).filter(pl.col("kind") == "json")
        records = [json.loads(t) for t in rows["text"].to_list()] if rows.height else []
        base = rows.select("step", "time", "topic", "source")
        if records and all(isinstance(r, dict) for r in records):
            fields = pl.DataFrame(records)
            fields = fields.rename({c: f"payload.{c}" for c in fields.columns if c in base.columns})
            return pl.concat([base, fields], how="horizontal")
        value = pl.Series("value", records, dtype=pl.Object) if records else pl.lit(None).alias("value")
        return base.with_columns(value)

    def decoded(self, pattern: str) -> list[Message]:
        """Messages on matching topics as :class:`caviar.Message` (arrays decoded lazily)."""
        out = []
        for r in self._select(pattern).iter_rows(named=True):
            body = r["text"] if r["kind"] != "binary" else r["data"]
            out.append(Message._from_wire(
                RawMessage(r["step"], r["time"], r["topic"], r["source"], r["kind"], body, r["meta"]), self.path))
        return out

    def module_times(self):
        """Per module, one row each in order of first appearance, the core's own
        (``caviar.core``) last: the core's totals, what ``caviar-core inspect`` prints.

        Columns: ``module``; ``steps`` run; ``wall_s`` (total) and ``mean_wall_s`` (per
        step) wall time; ``cpu_s`` CPU time; ``max_rss_mib`` the largest resident memory
        of its process after its stage (MiB); ``mean_gpu_util_pct`` mean GPU utilisation
        (%) and ``max_gpu_mem_mib`` largest GPU memory (MiB), both null without an NVIDIA
        GPU; ``msgs_in`` and ``msgs_out`` messages delivered to it and published by it;
        ``share`` of the run's wall time. (The core names some of them differently:
        ``rss_max_mib``, ``gpu_util_mean_pct``, ``gpu_mem_max_mib``.)"""
        import polars as pl

        rows = self.run.module_totals()
        schema = {"module": pl.String, "steps": pl.UInt32, "wall_s": pl.Float64, "cpu_s": pl.Float64,
                  "rss_max_mib": pl.Float64, "gpu_util_mean_pct": pl.Float64, "gpu_mem_max_mib": pl.Float64,
                  "msgs_in": pl.UInt64, "msgs_out": pl.UInt64}
        t = pl.DataFrame([{k: r.get(k) for k in schema} for r in rows], schema=schema)
        t = t.rename({"rss_max_mib": "max_rss_mib", "gpu_util_mean_pct": "mean_gpu_util_pct",
                      "gpu_mem_max_mib": "max_gpu_mem_mib"})
        return t.with_columns((pl.col("wall_s") / pl.col("steps")).alias("mean_wall_s"),
                              (pl.col("wall_s") / pl.col("wall_s").sum()).alias("share")).select(
            "module", "steps", "wall_s", "mean_wall_s", "cpu_s", "max_rss_mib", "mean_gpu_util_pct",
            "max_gpu_mem_mib", "msgs_in", "msgs_out", "share")

    def to_pandas(self, table: str = "messages"):
        """``messages`` or ``timings`` as a pandas DataFrame (needs pandas and pyarrow)."""
        return self.run.read(table).to_pandas()

    def __repr__(self) -> str:
        return (f"RunLog({str(self.path)!r}, status={self.status.get('status')!r}, "
                f"steps={self.status.get('steps_done')}, messages={self.messages.height})")


def load_run(path: str | os.PathLike) -> RunLog:
    """Loads a run directory written by ``caviar-core run``."""
    return RunLog(path)
