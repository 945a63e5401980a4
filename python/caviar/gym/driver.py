"""Runs episodes of a configuration in a thread of their own while the environment's
caller decides the agent module's actions.

The engine (:class:`caviar.Simulation`) runs an episode in the *engine thread*: the
episode is created, stepped and closed there (``caviar._core.Episode`` stays on the
thread that made it, and releases the GIL while it steps). When the agent module's
turn comes, its plugin, :class:`~caviar.gym.proxy.AgentProxy`, sends its inbox over a
local socket and waits; the caller's thread receives the inbox, computes the action
and sends the messages back. Everything the caller waits for arrives on one queue:

* ``("inbox", step, time, messages)`` from the socket's reader thread: the agent's turn;
* ``("step", messages)`` from the engine thread: a step finished, with all its messages;
* ``("end", run_status)``: the episode ended and its run directory is closed;
* ``("error", exception)``: the episode could not start, or a module failed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import queue
import shutil
import tempfile
import threading
from multiprocessing.connection import Connection, Listener
from typing import Any, Mapping, Sequence

from caviar import _core
from caviar.gym.proxy import from_wire
from caviar.plugin import Inbox, Message
from caviar.simulation import Simulation


@dataclasses.dataclass
class Turn:
    """The agent module's turn: its inbox at ``step``, and what ran since the last turn."""

    step: int
    time: float
    inbox: Inbox
    messages: list[Message]
    """Every message of the steps finished since the previous turn (the reward's)."""


@dataclasses.dataclass
class End:
    """The episode ended after the agent's last turn."""

    messages: list[Message]
    """Every message of the steps finished since the last turn."""
    status: dict[str, Any]
    """run.json of the closed run (``end_reason``: ``steps``, ``module`` or ``closed``)."""


class EpisodeDriver:
    """Episodes of ``config`` with module ``agent`` played from the calling thread."""

    def __init__(self, config: pathlib.Path, agent: str, subscribe: Sequence[str], overrides: list[str],
                 out: pathlib.Path):
        self.config = config
        self.agent = agent
        self.subscribe = list(subscribe)
        self.overrides = overrides
        self.out = out
        self.episodes = 0
        """The number of the last episode started: each start goes on from the episodes
        ``out`` holds then (a script run again with the same ``out`` adds episodes after them)."""
        self.run_dir: pathlib.Path | None = None
        self._events: queue.Queue = queue.Queue()
        self._socket_dir = pathlib.Path(tempfile.mkdtemp(prefix="caviar-gym-"))  # private (0700)
        self._address = str(self._socket_dir / "agent.sock")
        self._listener = Listener(self._address, family="AF_UNIX")
        self._conn: Connection | None = None
        self._closing = False
        self._running = False
        self._awaiting = False  # the agent module waits for our answer
        self._stop = threading.Event()
        self._commands: queue.Queue = queue.Queue()
        self._engine = threading.Thread(target=self._engine_loop, name=f"caviar-gym-engine-{agent}", daemon=True)
        self._reader = threading.Thread(target=self._read_loop, name=f"caviar-gym-reader-{agent}", daemon=True)
        self._engine.start()
        self._reader.start()

    # -- the caller's side -------------------------------------------------------------

    def start(self, seed: int, extra: Mapping[str, str] | None = None) -> Turn | End:
        """Ends the episode in progress, if any, and starts a new one with ``episode.seed
        = seed``; returns the agent's first turn (or the end, if it never got one)."""
        self.finish()
        # (after the episodes ``out`` holds now: another environment may have added some)
        self.episodes = max(self.episodes, last_episode(self.out)) + 1
        self._stop.clear()
        self.run_dir = self.out / f"episode-{self.episodes:04d}"
        overrides = [*self.overrides,
                     f"episode.seed={seed}",
                     f'modules.{self.agent}.plugin="caviar.gym.proxy:AgentProxy"',
                     f"modules.{self.agent}.params={{ address = {json.dumps(self._address)} }}",
                     f"modules.{self.agent}.subscribe={json.dumps(self.subscribe)}",
                     *(f"{k}={v}" for k, v in (extra or {}).items())]
        self._running = True
        self._commands.put((overrides, self.run_dir))
        return self._next()

    def answer(self, messages: list[tuple[str, Any]]) -> Turn | End:
        """Publishes ``messages`` as the agent module's step; returns its next turn or the end."""
        if not self._awaiting:
            raise RuntimeError(f"the agent module '{self.agent}' is not waiting for an action (no episode running: "
                               "call reset() first)")
        self._send(("publish", messages))
        return self._next()

    def finish(self) -> dict[str, Any] | None:
        """Ends the episode in progress (run.json: ``end_reason = "closed"``); its status."""
        if not self._running:
            return None
        self._stop.set()
        while True:
            if self._awaiting:  # the module publishes nothing; the episode ends after this step
                self._send(("skip",))
            event = self._next()
            if isinstance(event, End):
                return event.status

    def close(self) -> None:
        """Ends the episode in progress and stops the threads."""
        if self._closing:
            return
        try:
            self.finish()
        finally:
            self._closing = True
            self._commands.put(None)
            self._engine.join(timeout=60)
            try:  # wakes the reader from accept()
                from multiprocessing.connection import Client

                Client(self._address, family="AF_UNIX").close()
            except OSError:
                pass
            self._reader.join(timeout=10)
            self._listener.close()
            shutil.rmtree(self._socket_dir, ignore_errors=True)

    def _send(self, message: tuple) -> None:
        assert self._conn is not None
        self._awaiting = False
        try:
            self._conn.send(message)
        except OSError as e:
            raise RuntimeError(f"the agent module '{self.agent}' went away: {e}") from None

    def _next(self) -> Turn | End:
        """Waits for the agent's next turn or the end of the episode."""
        messages: list[Message] = []
        while True:
            event = self._events.get()
            kind = event[0]
            if kind == "hello":
                self._conn = event[1]
            elif kind == "inbox":
                _, step, time, wire = event
                self._awaiting = True
                return Turn(step, time, from_wire(wire), messages)
            elif kind == "step":
                messages.extend(event[1])
            elif kind == "end":
                self._running = self._awaiting = False
                return End(messages, event[1])
            elif kind == "error":
                self._running = self._awaiting = False
                raise event[1]

    # -- the engine thread ---------------------------------------------------------------

    def _engine_loop(self) -> None:
        while True:
            command = self._commands.get()
            if command is None:
                return
            overrides, run_dir = command
            try:
                sim = Simulation.from_toml(self.config, overrides=overrides, out=run_dir)
            except BaseException as e:  # a bad configuration: the caller raises it
                self._events.put(("error", e))
                continue
            try:
                while not sim.done and not self._stop.is_set():
                    messages = sim.step()
                    if messages is None:
                        break
                    self._events.put(("step", messages))
                sim.close()
                self._events.put(("end", json.loads(_core.run_status(sim.run_dir))))
            except BaseException as e:  # a module failed: the run is closed as failed
                # Without this thread's frames: they hold the episode, which must be dropped here.
                self._events.put(("error", e.with_traceback(None)))
            finally:
                del sim

    # -- the socket's reader thread ------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._closing:
            try:
                conn = self._listener.accept()
            except OSError:
                return
            if self._closing:
                conn.close()
                return
            try:
                while True:
                    message = conn.recv()
                    if message[0] == "hello":
                        self._events.put(("hello", conn))
                    else:
                        self._events.put(message)
            except (EOFError, OSError):
                conn.close()


def last_episode(out: pathlib.Path) -> int:
    """The highest number of the ``episode-NNNN`` run directories in ``out`` (0: none)."""
    numbers = [int(p.name[len("episode-"):]) for p in out.glob("episode-*") if p.name[len("episode-"):].isdigit()]
    return max(numbers, default=0)


def default_out() -> pathlib.Path:
    """A fresh directory for an environment's runs."""
    return pathlib.Path(tempfile.mkdtemp(prefix="caviar-gym-runs-"))


def pythonpath_env() -> dict[str, str]:
    """This process's environment with its import path, for a subprocess that must import
    the same plugins."""
    import sys

    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
