"""Exceptions of caviar."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration problem.

    Raised by the core with a complete message (``file:line: key: what was expected``).
    Plugins raise it from parameter checks with ``key`` relative to their
    ``[modules.NAME]`` table (e.g. ``"params.speed"``); the core adds file and line.
    """

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.message = message
        self.key = key


class ConfigWarning(UserWarning):
    """A configuration that runs but may not do what was meant (a UE type no module
    publishes). Plugins issue it from parameter checks with ``warnings.warn``, ``key``
    relative to the table being checked; ``caviar-core validate`` and ``run`` print it as
    ``warning: modules.NAME.params.KEY: …``."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.message = message
        self.key = key


class RunError(RuntimeError):
    """A run stopped: a module failed or the run was interrupted.

    What was recorded up to then is in ``run_dir`` and can be read with
    :func:`caviar.load_run`.
    """

    def __init__(self, message: str, module: str | None = None, phase: str | None = None,
                 step: int | None = None, run_dir: str | None = None):
        super().__init__(message)
        self.module = module
        self.phase = phase
        self.step = step
        self.run_dir = run_dir
