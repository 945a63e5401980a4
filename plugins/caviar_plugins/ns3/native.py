"""ns-3 in this process: loading it (:func:`load`), and calls into it that cannot take the
process down (:func:`guarded`).

ns-3 ends the process on a fatal error (``NS_FATAL_ERROR``, a failed ``NS_ASSERT``: it
writes why to ``std::cerr`` and calls ``std::terminate``), and cling's crash handler then
prints a gdb backtrace of about 160 lines. A guarded call turns that into
:class:`Ns3Aborted`, whose message is ns-3's own words in one line (``Could not parse rate:
fast (data-rate.cc:246)``); what ns-3 wrote in full is a note on the exception, so it goes
with the traceback, not into the one-line message.
"""

from __future__ import annotations

import contextlib
import functools
import os
import pathlib
import re
import sys
import tempfile
from typing import Any, Callable, Iterator

HEADERS = frozenset({"core", "network", "internet", "point-to-point", "mobility", "lte", "propagation",
                     "spectrum", "traffic-control", "applications"})
"""The ns-3 modules whose headers cppyy parses (their own includes bring the rest): the
wheel's loader parses all 40-odd modules' (5.3 s on the 2-core machine), these 2.4 s. Every
library is loaded all the same."""

NOISE = "Failed to materialize symbols"
"""What cling says on the C-level stderr as it loads ns-3, harmlessly (static initialisers
it runs twice): held back by :func:`load` unless the load fails."""


class Ns3Unavailable(ImportError):
    """The ``ns3`` package is not installed (``pip install -e 'plugins[ns3]'``)."""


class Ns3Aborted(RuntimeError):
    """ns-3 aborted inside a call (a fatal error, a failed assertion, a crash); the message
    is ns-3's own, in one line. The network it happened in cannot go on."""

    __notes__: list[str]


@functools.cache
def load() -> Any:
    """Imports ns-3 and compiles the plugin's C++ half, once per process (about 3 s: cppyy
    parses the :data:`HEADERS` modules' headers). Returns cppyy's global namespace."""
    # A fatal error in a guarded call becomes an exception: no gdb backtrace first (it takes
    # seconds, during which a NATS worker sends no heartbeat).
    os.environ.setdefault("CPPYY_CRASH_QUIET", "1")
    with _held_back_stderr():
        try:
            import cppyy

            if "ns" in sys.modules:
                from ns import ns  # noqa: F401  (someone loaded it whole already)
            else:
                _import_ns(cppyy)
        except ImportError as e:  # pragma: no cover - the test environment installs it
            raise Ns3Unavailable("the ns3-network plugin needs ns-3: pip install -e 'plugins[ns3]' "
                                 f"(PyPI's ns3 3.44 wheel); import failed: {e}") from e
        cppyy.cppdef((pathlib.Path(__file__).with_name("caviar_ns3.h")).read_text())
        cppyy.gbl.caviar_ns3.Errors()  # std::cerr keeps its tail from now on
    return cppyy.gbl


def _import_ns(cppyy: Any) -> None:
    """``from ns import ns``, with cppyy including only the :data:`HEADERS` modules' headers."""
    include = cppyy.include

    def some(header: str, *args: Any, **kwargs: Any) -> Any:
        module = header.removeprefix("ns3/").removesuffix("-module.h")
        if header.startswith("ns3/") and header.endswith("-module.h") and module not in HEADERS:
            return True
        return include(header, *args, **kwargs)

    cppyy.include = some
    try:
        from ns import ns  # noqa: F401  (loads the ns-3 libraries)
    finally:
        cppyy.include = include


@contextlib.contextmanager
def _held_back_stderr() -> Iterator[None]:
    """What the block writes to file descriptor 2 (C, C++ and Python alike) is held back
    and passed on after it, less cling's :data:`NOISE`; all of it if the block fails."""
    sys.stderr.flush()
    saved = os.dup(2)
    ok = False
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
            ok = True
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            lines = held.read().decode(errors="replace").splitlines(keepends=True)
            text = "".join(line for line in lines if not ok or NOISE not in line)
            if text:
                sys.stderr.write(text)
                sys.stderr.flush()


_FATAL = re.compile(r'msg="(.*?)",\s*(?:\+?[\d.]+s\s+-?\d+\s+)?file=(\S+), line=(\d+)', re.S)
"""ns-3's report of a fatal error: ``msg="…", file=…, line=…`` (a failed assertion puts
``NS_ASSERT failed, cond="…", `` before it; with logging on, a time and a node come between)."""


def ns3_words(text: str) -> str:
    """ns-3's report of a fatal error (what it wrote to stderr) in one line: the message and
    the source file and line (``name Bogus is not a valid enum value. … (enum.h:293)``)."""
    found = _FATAL.findall(text)
    if found:
        msg, file, line = found[-1]
        return f"{' '.join(msg.split())} ({file.rsplit('/', 1)[-1]}:{line})"
    lines = [ln.strip() for ln in text.splitlines()
             if ln.strip() and "NS_FATAL, terminating" not in ln and not ln.startswith("terminate called")]
    return "; ".join(lines)


_CRASH = r"\b(AbortSignal|SegmentationViolation|BusError|IllegalInstruction): "
"""How cppyy names a signal it turned into an exception (cppyy.ll.FatalError's kinds)."""

_depth = 0
"""Guarded calls in progress (one may call another: the policy is set at the outermost)."""


@contextlib.contextmanager
def guarded(what: str, on_abort: Callable[[str], None] | None = None) -> Iterator[None]:
    """ns-3 calls inside the block that abort (``NS_FATAL_ERROR``, a failed assertion,
    SIGSEGV) raise :class:`Ns3Aborted` ("ns-3 aborted WHAT: its message") instead of ending
    the process. ``on_abort(words)`` is told first. ns-3's state is then undefined: the
    network must not be used again."""
    global _depth
    import cppyy.ll

    errors = load().caviar_ns3.Errors()
    mark = errors.Written()
    if _depth == 0:
        cppyy.ll.set_signals_as_exception(True)
        errors.Hold(True)  # ns-3's words come once, in the exception, if it aborts
    _depth += 1
    try:
        yield
    except (cppyy.ll.FatalError, TypeError) as e:
        # (An overloaded call reports its overloads' failures as one TypeError.)
        crash = [ln.strip() for ln in str(e).splitlines() if re.search(_CRASH, ln)]
        if isinstance(e, TypeError) and not crash:
            raise
        errors.Drop()
        said = str(errors.Since(mark))
        words = ns3_words(said) or (crash or [str(e)])[-1]  # "SegmentationViolation: segfault in C++; …"
        if on_abort is not None:
            on_abort(words)
        error = Ns3Aborted(f"ns-3 aborted {what}: {words}")
        if said.strip():  # (add_note from Python 3.11 on: the traceback shows it)
            error.__notes__ = ["What ns-3 wrote:\n" + said.rstrip()]
        raise error from None
    finally:
        _depth -= 1
        if _depth == 0:
            errors.Hold(False)
            cppyy.ll.set_signals_as_exception(False)
