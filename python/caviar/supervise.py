"""``caviar-core run`` under a supervising parent: a run never ends silently.

The engine runs in a child process (the same command, marked ``CAVIAR_SUPERVISED=1``).
However the child ends, this parent is left to say how: a run that closed itself
(completed, failed, interrupted, refused: exit 0, 1, 130, 2) passes its exit status
through; a child that ended without closing its run (a plugin's ``os._exit``, a
segmentation fault in native code, the kernel's out-of-memory killer) is reported at
once, naming the module and the step that were running (``progress.json``) and the
cause (exit status, or signal, and "out of memory" when the kernel's cgroup counted an
OOM kill), and its ``run.json`` is closed as ``failed`` with that error (exit 1).

Signals: the child has a process group of its own, so Ctrl-C in a terminal reaches it
once, through this parent, which forwards SIGINT and SIGTERM; the child dies with its
parent (``PR_SET_PDEATHSIG``), so ``kill -9`` of the command leaves an abandoned run,
as before. ``CAVIAR_SUPERVISED=1`` in the environment runs the engine in this process.
"""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import tempfile
from typing import Any

from caviar.rundir import RunDir

ENV_CHILD = "CAVIAR_SUPERVISED"
ENV_RUN_DIR_FILE = "CAVIAR_RUN_DIR_FILE"
OOM_EVENTS = pathlib.Path("/sys/fs/cgroup/memory.events")
NORMAL_EXITS = (0, 1, 2, 130)
SIGNAL_TEXT = {
    signal.SIGSEGV: "crashed with a segmentation fault (SIGSEGV)",
    signal.SIGBUS: "crashed with a bus error (SIGBUS)",
    signal.SIGABRT: "aborted (SIGABRT)",
    signal.SIGFPE: "crashed with a floating-point exception (SIGFPE)",
    signal.SIGILL: "crashed with an illegal instruction (SIGILL)",
    signal.SIGKILL: "was killed (SIGKILL)",
}


def supervised() -> bool:
    """Whether this process is the supervised child (the engine runs here)."""
    return os.environ.get(ENV_CHILD) == "1"


def oom_kills() -> int | None:
    """The OOM kills the kernel counted in this cgroup (v2), if it says."""
    try:
        for line in OOM_EVENTS.read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == "oom_kill":
                return int(value)
    except (OSError, ValueError):
        pass
    return None


def cause(returncode: int, oom_before: int | None, oom_after: int | None) -> str:
    """What ended a child that did not close its run, in words."""
    if returncode < 0:
        sig = signal.Signals(-returncode)
        if sig == signal.SIGKILL and oom_before is not None and oom_after is not None and oom_after > oom_before:
            return "ran out of memory: the kernel's OOM killer ended it (SIGKILL)"
        return SIGNAL_TEXT.get(sig, f"was ended by {sig.name}")
    return f"exited with status {returncode} without closing the run (os._exit or a native exit in a plugin?)"


def _in_child() -> None:
    """Before the child's exec: a process group of its own (a terminal's Ctrl-C reaches it
    once, through the parent), and death with its parent (Linux)."""
    os.setpgid(0, 0)
    if sys.platform == "linux":
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)


def run(argv: list[str]) -> int:
    """Runs ``argv`` (``caviar-core run …``) in a supervised child; returns the exit status."""
    with tempfile.TemporaryDirectory(prefix="caviar-supervise-") as tmp:
        note = pathlib.Path(tmp) / "run-dir"
        env = dict(os.environ, **{ENV_CHILD: "1", ENV_RUN_DIR_FILE: str(note)})
        before = oom_kills()
        child = subprocess.Popen([sys.executable, "-m", "caviar.cli", *argv[1:]], env=env, preexec_fn=_in_child)

        def forward(signum, _frame):
            try:
                child.send_signal(signum)
            except ProcessLookupError:
                pass

        previous = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            code = child.wait()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        run_dir = pathlib.Path(note.read_text()) if note.exists() else None
    if run_dir is None or _status(run_dir).get("status") not in ("running", "abandoned"):
        if code < 0 and run_dir is None:
            print(f"error: caviar-core run {cause(code, before, oom_kills())} before its run began",
                  file=sys.stderr)
            return 1
        return code if code >= 0 else 1
    message = f"the process {cause(code, before, oom_kills())}"
    try:
        where = RunDir(run_dir).close_failed(message) or ""
    except (OSError, ValueError) as e:  # (run.json unreadable or unwritable: say so, and what happened)
        where = f" (the run could not be closed: {e})"
    print(f"error: {run_dir}: the run ended abnormally: {message}{where}", file=sys.stderr)
    return 1


def _status(run_dir: pathlib.Path) -> dict[str, Any]:
    try:
        return RunDir(run_dir).status()
    except (OSError, ValueError):
        return {}
