"""CAVIAR: co-simulation of 6G communications, 3D scenarios and AI for digital twins.

The engine is Rust (``caviar._core``); this package is its Python face: the plugin
API (:class:`Plugin`), episodes driven from Python (:class:`Simulation`) and
recorded runs (:func:`load_run`).
"""

from caviar._core import __version__
from caviar.errors import ConfigError, ConfigWarning, RunError
from caviar.plugin import Artifact, Context, Inbox, Message, Plugin, apply_preset, given_keys
from caviar.runlog import RunLog, RunStatus, load_run
from caviar.simulation import Simulation
from caviar.topics import matches

END_TOPIC = "caviar.episode.end"
"""Publishing on this topic ends the episode after the current step."""
STATUS_TOPIC = "caviar.status"
"""A module's one-line status for people (a string, e.g. what share of its work a cache
served): ``caviar-core run`` shows each module's latest beside its progress."""

__all__ = [
    "Artifact", "ConfigError", "ConfigWarning", "Context", "END_TOPIC", "Inbox", "Message", "Plugin", "RunError",
    "RunLog", "RunStatus", "STATUS_TOPIC", "Simulation", "__version__", "apply_preset", "given_keys", "inspect",
    "load_run", "matches",
]


def inspect(run_dir) -> str:
    """The summary ``caviar-core inspect RUN_DIR`` prints."""
    from caviar import _core

    return _core.inspect(str(run_dir))
