"""Subcommands that installed packages add through the ``caviar.commands`` entry points."""

import pytest

from caviar import cli as caviar_cli


class _EntryPoint:
    def __init__(self, name, fn):
        self.name, self._fn = name, fn

    def load(self):
        return self._fn


def test_packages_add_subcommands_through_entry_points(monkeypatch, capfd):
    seen = []
    eps = [_EntryPoint("scene", lambda argv: seen.append(argv) or 3),
           _EntryPoint("run", lambda argv: pytest.fail("core commands are never shadowed"))]
    monkeypatch.setattr(caviar_cli.metadata, "entry_points",
                        lambda group: eps if group == caviar_cli.COMMANDS_GROUP else [])
    assert caviar_cli.dispatch(["caviar", "scene", "build", "--x"]) == 3
    assert seen == [["build", "--x"]]
    assert caviar_cli.dispatch(["caviar", "--help"]) == 0
    assert "validate" in capfd.readouterr().out
    assert caviar_cli.dispatch(["caviar", "nonsense"]) == 2
