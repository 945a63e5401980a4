"""Console entry point of ``caviar-core`` / ``caviar``: the command line is the core's
(Rust); ``report`` (figures with matplotlib) and ``worker`` (a module over NATS) are the
Python side's, and installed packages add their own commands.

A package adds a subcommand with an entry point of group ``caviar.commands``: its
name is the subcommand, its value a callable that takes the arguments after the
subcommand (a list of str) and returns the exit code::

    [project.entry-points."caviar.commands"]
    scene = "caviar_scene.cli:main"

Built-in commands win over packages' commands of the same name.
"""

from __future__ import annotations

import sys
from importlib import metadata
from typing import Callable

from caviar import supervise

COMMANDS_GROUP = "caviar.commands"

# The core's own subcommands (and its help): never looked up among entry points.
_CORE_COMMANDS = {"run", "validate", "inspect", "help"}


def _report(argv: list[str]) -> int:
    from caviar.report import main as report

    return report(argv)


def _worker(argv: list[str]) -> int:
    from caviar.worker import main as worker

    return worker(argv)


_BUILTIN: dict[str, Callable[[list[str]], int]] = {"report": _report, "worker": _worker}


def package_command(name: str) -> Callable[[list[str]], int] | None:
    """The callable an installed package registered as subcommand ``name``, if any."""
    if name in _CORE_COMMANDS or name.startswith("-"):
        return None
    for ep in metadata.entry_points(group=COMMANDS_GROUP):
        if ep.name == name:
            return ep.load()
    return None


def dispatch(argv: list[str]) -> int:
    """Runs ``argv`` (``argv[0]`` is the program name); returns the exit code."""
    argv = list(argv)
    argv[0] = "caviar-core"
    if len(argv) > 1:
        command = _BUILTIN.get(argv[1]) or package_command(argv[1])
        if command is not None:
            code = command(argv[2:])
            return 0 if code is None else int(code)
    if len(argv) > 1 and argv[1] == "run" and not supervise.supervised() and not {"-h", "--help"} & set(argv):
        return supervise.run(argv)  # the engine in a child: however it ends, this process says so
    from caviar import _core

    return _core.main(argv)


def main() -> None:
    sys.exit(dispatch(sys.argv))


if __name__ == "__main__":
    main()
