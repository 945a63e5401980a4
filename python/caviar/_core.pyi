"""The Rust core of CAVIAR (``caviar_core``, built by maturin as ``caviar._core``).

Hosts Python plugins in-process, drives episodes from Python and shares the core's
topic matching and NATS wire format with the Python side. Not a public API: use
:mod:`caviar` (``caviar.Simulation``, ``caviar.matches``, ``caviar.inspect``).
"""

from __future__ import annotations

import os
import pathlib
from typing import Callable, Iterable, Literal, Optional, final

__version__: str
"""The version of the core (and of the caviar package)."""

PROTOCOL: int
"""Version of the NATS step protocol (docs/nats-protocol.md) this core speaks."""

PayloadKind = Literal["json", "binary", "artifact"]

OutgoingTuple = tuple[str, PayloadKind, "str | bytes", Optional[str]]
"""A published message as the core takes it from ``caviar._host``:
``(topic, kind, body, meta)``; ``body`` is JSON text, the artifact's path relative
to the run directory, or the bytes of a binary payload described by ``meta``."""

@final
class RawMessage:
    """A routed message as it crosses from the core: :class:`caviar.Message` is made
    of it (``Message._from_wire``) and decodes the payload only when asked."""

    def __new__(
        cls,
        step: int,
        time: float,
        topic: str,
        source: str,
        kind: PayloadKind,
        body: str | bytes,
        meta: Optional[str] = None,
    ) -> RawMessage: ...
    @property
    def step(self) -> int:
        """The step it was published in."""
    @property
    def time(self) -> float:
        """Virtual time of that step, seconds."""
    @property
    def topic(self) -> str: ...
    @property
    def source(self) -> str:
        """The publishing module's name."""
    @property
    def kind(self) -> PayloadKind: ...
    @property
    def body(self) -> str | bytes:
        """``str`` for JSON (its text) and artifacts (the path in the run directory),
        ``bytes`` for binary payloads."""
    @property
    def meta(self) -> Optional[str]:
        """JSON text describing a binary body (``dtype``, ``shape``, …); None otherwise."""

@final
class StepRequest:
    """A step request of the NATS protocol, decoded by :func:`decode_request`."""

    @property
    def protocol(self) -> int: ...
    @property
    def step(self) -> int: ...
    @property
    def time(self) -> float: ...
    @property
    def shard(self) -> int:
        """Which piece of the step this request asks for (0-based)."""
    @property
    def shards(self) -> int:
        """How many pieces the step is split into."""
    @property
    def messages(self) -> list[RawMessage]:
        """The module's inbox, in delivery order."""

@final
class Guard:
    """A worker's side of the run's authentication: the run key (64 hex digits, or
    from ``CAVIAR_RUN_KEY`` / ``CAVIAR_RUN_KEY_FILE`` when ``key`` is None), the core's
    sequence numbers seen, the worker's own counter and its step schedule."""

    def __new__(cls, run: str, key: Optional[str] = None) -> Guard: ...
    def seal(self, subject: str, body: bytes) -> bytes:
        """``body`` with this worker's next sequence number and its HMAC for ``subject``."""
    def open(self, subject: str, frame: bytes) -> bytes:
        """The body of a frame of the core received on ``subject``; ValueError (counted)
        if it fails authentication or repeats a sequence number."""
    def schedule(self, every: int, offset: int, steps: Optional[int], shards: int, exclusive: bool) -> None: ...
    def resume_at(self, next_step: int) -> None: ...
    def accept_step(self, step: int, shard: int) -> None:
        """ValueError (counted) for a step out of sequence."""
    def refuse(self) -> None:
        """Counts a refusal decided by the worker."""
    @property
    def rejected(self) -> int:
        """Frames refused so far."""

def sign(key: str, run: str, subject: str, seq: int, body: bytes) -> bytes:
    """``body`` sealed with the run key ``key`` (hex) for ``subject`` of run ``run``."""

def verify(key: str, run: str, subject: str, frame: bytes) -> tuple[int, bytes]:
    """``(seq, body)`` of a sealed frame; ValueError when it fails authentication."""

@final
class Episode:
    """An episode driven from Python; :class:`caviar.Simulation` wraps it.

    Creating one loads the configuration and the plugins and creates the run
    directory; raises :class:`caviar.ConfigError` before anything runs if the
    configuration is wrong, :class:`OSError` if the run directory cannot be made.
    """

    def __new__(
        cls,
        path: str | os.PathLike[str],
        overrides: list[str],
        out: Optional[str | os.PathLike[str]] = None,
    ) -> Episode: ...
    def step(self) -> Optional[list[RawMessage]]:
        """Runs one step; returns its messages, or None when the episode is over.

        Raises :class:`caviar.RunError` if a module fails (the episode is then closed).
        """
    def run(self, progress: Optional[Callable[[int, Optional[int], float], object]] = None) -> None:
        """Runs to the end and closes the episode. ``progress`` is called with (steps
        done, planned steps or None, wall seconds) after every step; an exception in it
        or Ctrl-C interrupts the run (:class:`caviar.RunError`)."""
    def close(self) -> None:
        """Tears down the modules, compacts the recording and writes run.json
        (``end_reason = "closed"`` when the episode had not ended)."""
    @property
    def run_dir(self) -> pathlib.Path: ...
    @property
    def steps_done(self) -> int: ...
    @property
    def planned_steps(self) -> Optional[int]:
        """Steps in the episode, or None when a module ends it."""
    @property
    def ts(self) -> float:
        """Sampling interval Ts, seconds."""
    @property
    def done(self) -> bool: ...
    @property
    def wall_s(self) -> float:
        """Wall-clock seconds spent in steps so far."""
    @property
    def warnings(self) -> list[str]:
        """Wiring warnings of the run's modules (a subscription nothing publishes, a
        topic nobody reads), as ``caviar-core validate`` prints them; with
        ``episode.strict_wiring`` they refuse the run instead."""

def main(argv: list[str]) -> int:
    """The ``caviar-core`` command line (``run``, ``validate``, ``inspect``); returns
    the exit code: 0 success, 1 the run failed, 2 bad input, 130 interrupted."""

def table_files(run_dir: str | os.PathLike[str], table: str) -> list[pathlib.Path]:
    """The Parquet files holding table ``table`` (``"messages"`` or ``"timings"``) of
    RUN_DIR, in order: ``[RUN_DIR/TABLE.parquet]`` once the run was compacted, else the
    parts ``RUN_DIR/TABLE/part-NNNNNN.parquet`` of a run in progress or killed (an empty
    list before its first flush). ValueError when RUN_DIR has neither. The one place
    that knows the run directory's layout (:class:`caviar.rundir.RunDir` reads through
    it)."""

def module_totals(run_dir: str | os.PathLike[str]) -> str:
    """Per-module totals of RUN_DIR's timings as JSON text: a list of objects
    ``{"module", "steps", "wall_s", "cpu_s", "rss_max_mib", "msgs_in", "msgs_out",
    "gpu_util_mean_pct", "gpu_mem_max_mib"}`` (GPU fields null where none was measured),
    in order of first appearance with the core's own row last: what ``caviar-core
    inspect`` shows. ValueError when RUN_DIR has no timings."""

def close_failed_run(run_dir: str | os.PathLike[str], message: str) -> str | None:
    """Closes the run.json a dead process left ``running`` as ``failed`` with ``message``
    followed by where it was (progress.json: the module started last and its step); returns
    that place in words, or None when the run is not running. ValueError if run.json cannot
    be read or written (naming the file)."""

def run_dir_files() -> dict[str, str]:
    """The names of a run directory's files, as the core writes them: ``status`` (run.json),
    ``progress``, ``config`` (the configuration run, overrides applied), ``checkpoint``."""

def compacted_file(table: str) -> str:
    """The file a recorded table (``messages``, ``timings``) is compacted into when its run
    ends (``messages.parquet``)."""

def run_status(run_dir: str | os.PathLike[str]) -> str:
    """run.json as JSON text, with what a reader concludes about a run left running:
    ``status`` ``abandoned`` when its process is gone (and ``abandoned``, in words),
    ``last_step``/``last_stage``/``last_modules`` from progress.json. ValueError if it
    cannot be read (naming the file)."""

def inspect(run_dir: str | os.PathLike[str]) -> str:
    """The text ``caviar-core inspect RUN_DIR`` prints; ValueError if it is not a run
    directory."""

def matches(pattern: str, topic: str) -> bool:
    """True if ``topic`` matches the NATS subject ``pattern`` (``*``: one token,
    ``>``: one or more remaining tokens). ValueError if the pattern is not valid
    (an empty token as in ``a..b``, a wildcard inside a token, ``>`` not last)."""

def resident_mib() -> float:
    """Resident memory of this process in MiB (NaN where it cannot tell)."""

def decode_request(frame: bytes) -> StepRequest:
    """Decodes a step request frame of the NATS protocol; ValueError if it is
    malformed or speaks another protocol version."""

def encode_reply(
    out: Iterable[OutgoingTuple],
    wall_s: float,
    cpu_s: float,
    rss_mib: Optional[float] = None,
    gpu: Optional[tuple[float, float]] = None,
) -> bytes:
    """Encodes a successful step reply frame: the step's messages and what it cost
    (wall and CPU seconds, resident MiB, GPU utilisation % and GPU MiB)."""

def encode_failure(message: str, trace: Optional[str] = None, key: Optional[str] = None) -> bytes:
    """Encodes a failed step reply frame. ``key``: for a configuration error, the key
    under ``modules.NAME``."""
