"""Checks of the tools' command-line flags, made before any work starts: each failure is a
:class:`FlagError` whose message begins with the flag (``--out: ...``), which the commands
print as one line and exit 2 on."""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import tempfile
from typing import Any


class Usage(Exception):
    """A command line argparse refuses (a missing or unknown flag, a bad choice): printed as
    one line, exit 2."""


class Parser(argparse.ArgumentParser):
    """argparse's parser that raises :class:`Usage` instead of printing its usage and exiting,
    so that each tool prints one line of its own."""

    def error(self, message):  # one line, exit 2 (argparse's own convention)
        raise Usage(message)


class FlagError(ValueError):
    """A flag's value the command cannot use; the message names the flag."""

    def __init__(self, flag: str, message: str):
        super().__init__(f"{flag}: {message}")
        self.flag = flag


def _writable_dir(path: pathlib.Path) -> bool:
    """Whether a file can be created in the existing directory ``path`` (tried: a read-only
    file system or a root-owned folder answer no, whoever runs)."""
    try:
        fd, name = tempfile.mkstemp(dir=path, prefix=".caviar-probe-")
    except OSError:
        return False
    os.close(fd)
    os.unlink(name)
    return True


def output_dir(path: pathlib.Path, flag: str = "--out") -> pathlib.Path:
    """A folder the command writes into (created if missing): not a file, and writable
    where it is or where it would be created."""
    if path.exists():
        if not path.is_dir():
            raise FlagError(flag, f"{path} is a file, not a folder to write into")
        if not _writable_dir(path):
            raise FlagError(flag, f"{path} cannot be written (permission or a read-only file system)")
        return path
    return _creatable(path, flag)


def new_output(path: pathlib.Path, flag: str) -> pathlib.Path:
    """A file or folder the command creates: it must not exist yet, and its folder must be writable."""
    if path.exists():
        raise FlagError(flag, f"{path} already exists; give a new name")
    return _creatable(path, flag)


def _creatable(path: pathlib.Path, flag: str) -> pathlib.Path:
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise FlagError(flag, f"{path} cannot be created: {parent} is a file, not a folder")
    if not _writable_dir(parent):
        raise FlagError(flag, f"{path} cannot be created: {parent} cannot be written (permission or a read-only "
                              "file system)")
    return path


def existing_file(path: pathlib.Path, flag: str, what: str = "a file") -> pathlib.Path:
    if not path.exists():
        raise FlagError(flag, f"{path} does not exist (expected {what})")
    if not path.is_file():
        raise FlagError(flag, f"{path} is a folder (expected {what})")
    if not os.access(path, os.R_OK):
        raise FlagError(flag, f"{path} cannot be read")
    return path


def existing_dir(path: pathlib.Path, flag: str, what: str = "a folder") -> pathlib.Path:
    if not path.exists():
        raise FlagError(flag, f"{path} does not exist (expected {what})")
    if not path.is_dir():
        raise FlagError(flag, f"{path} is a file (expected {what})")
    return path


def json_file(path: pathlib.Path, flag: str, what: str = "a JSON file") -> Any:
    """The parsed contents of a JSON file."""
    existing_file(path, flag, what)
    try:
        return json.loads(path.read_text())
    except UnicodeDecodeError:
        raise FlagError(flag, f"{path} is not text (expected {what})") from None
    except json.JSONDecodeError as e:
        raise FlagError(flag, f"{path} is not JSON (line {e.lineno}, column {e.colno}: {e.msg}; expected {what})") \
            from None


def integer(value: int, flag: str, minimum: int = 0, maximum: int | None = None) -> int:
    if value < minimum or (maximum is not None and value > maximum):
        bound = f"from {minimum} to {maximum}" if maximum is not None else f"at least {minimum}"
        raise FlagError(flag, f"expected a whole number {bound}, got {value}")
    return value


def number(value: float, flag: str, positive: bool = False, minimum: float | None = None) -> float:
    if not math.isfinite(value):
        raise FlagError(flag, f"expected a finite number, got {value}")
    if positive and not value > 0:
        raise FlagError(flag, f"expected a positive number, got {value:g}")
    if minimum is not None and value < minimum:
        raise FlagError(flag, f"expected a number of at least {minimum:g}, got {value:g}")
    return value


def numbers(text: str, flag: str, count: int, names: str) -> tuple[float, ...]:
    """``count`` finite numbers written ``A,B,...`` (``names`` says which, e.g. ``X,Y``)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise FlagError(flag, f"expected {names} (numbers), got {text!r}") from None
    if len(values) != count:
        raise FlagError(flag, f"expected {names}: {count} numbers, got {len(values)} in {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise FlagError(flag, f"expected {names} as finite numbers, got {text!r}")
    return values
