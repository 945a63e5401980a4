"""Driving an episode from Python (a notebook, a test, a sweep script)."""

from __future__ import annotations

import json
import os
import pathlib
import sys
import time
import warnings
from typing import Any, Iterable, Mapping

from caviar import _core
from caviar.plugin import Message
from caviar.runlog import RunLog, load_run


class WiringWarning(UserWarning):
    """A subscription no module publishes, or a published topic nobody reads."""


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, str, list)):
        return json.dumps(value)  # JSON scalars and simple arrays are valid TOML
    raise TypeError(f"override value {value!r}: expected a bool, number, string or list")


def _overrides(overrides: Mapping[str, Any] | Iterable[str] | None) -> list[str]:
    if overrides is None:
        return []
    if isinstance(overrides, (str, bytes)):
        raise TypeError(f"overrides: expected a mapping ({{'episode.steps': 5}}) or a list of 'KEY=VALUE' "
                        f"strings, got the string {overrides!r} (put it in a list)")
    if isinstance(overrides, Mapping):
        return [f"{k}={_toml_value(v)}" for k, v in overrides.items()]
    return [str(o) for o in overrides]


class Simulation:
    """One episode of a configuration.

    >>> sim = caviar.Simulation.from_toml("blueprints/quickstart/config.toml",
    ...                                    overrides={"episode.steps": 10})
    >>> for m in sim.step(): print(m.topic, m.data)      # one step at a time
    >>> log = sim.run()                                   # or the rest of the episode
    >>> log.topic("communications.throughput")            # a polars DataFrame
    """

    def __init__(self, episode: "_core.Episode"):
        self._episode = episode
        for w in episode.warnings:
            warnings.warn(f"wiring: {w}", WiringWarning, stacklevel=3)

    @classmethod
    def from_toml(cls, path: str | os.PathLike, overrides: Mapping[str, Any] | Iterable[str] | None = None,
                  out: str | os.PathLike | None = None) -> "Simulation":
        """Loads the configuration, the plugins and creates the run directory.

        ``overrides``: ``{"episode.steps": 10}`` or ``["episode.steps=10"]``, as ``--set``.
        ``out``: the run directory (default ``output.dir/NAME-NNN``).
        Raises :class:`caviar.ConfigError` before anything runs if the config is wrong
        (or, with ``episode.strict_wiring``, if its modules are not wired together);
        otherwise wiring problems are issued as :class:`WiringWarning`.
        """
        return cls(_core.Episode(pathlib.Path(path), _overrides(overrides),
                                 None if out is None else pathlib.Path(out)))

    @property
    def run_dir(self) -> pathlib.Path:
        return pathlib.Path(self._episode.run_dir)

    @property
    def ts(self) -> float:
        return self._episode.ts

    @property
    def steps_done(self) -> int:
        return self._episode.steps_done

    @property
    def time(self) -> float:
        """Virtual time of the next step."""
        return self._episode.steps_done * self._episode.ts

    @property
    def done(self) -> bool:
        return self._episode.done

    def step(self) -> list[Message] | None:
        """Runs one step; returns the messages published in it, or None at the end.

        Raises :class:`caviar.RunError` if a module fails (the run is then closed).
        """
        raw = self._episode.step()
        if raw is None:
            return None
        run_dir = self.run_dir
        return [Message._from_wire(r, run_dir) for r in raw]

    def run(self, progress: bool = False) -> RunLog:
        """Runs to the end of the episode, closes it and returns the recorded log."""
        callback = _Progress(sys.stderr) if progress else None
        self._episode.run(callback)
        if callback:
            callback.finish()
        return load_run(self.run_dir)

    def close(self) -> None:
        """Ends the episode early: teardown, flush, ``run.json``."""
        self._episode.close()

    def __enter__(self) -> "Simulation":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Simulation({str(self.run_dir)!r}, steps_done={self.steps_done})"


class _Progress:
    """One status line: steps, virtual time, RTF, ETA."""

    def __init__(self, stream):
        self.stream = stream
        self.last = 0.0

    def __call__(self, done: int, planned: int | None, wall: float) -> None:
        now = time.monotonic()
        if now - self.last < 0.2 and done != planned:
            return
        self.last = now
        total = f"/{planned}" if planned else ""
        eta = ""
        if planned and done:
            eta = f"  ETA {wall / done * (planned - done):.1f} s"
        self.stream.write(f"\rstep {done}{total}  wall {wall:.1f} s{eta}   ")
        self.stream.flush()

    def finish(self) -> None:
        self.stream.write("\n")
