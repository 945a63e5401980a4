"""A Griffe extension for the documentation site (mkdocs.yml): the docstrings are written
as prose with Sphinx roles (``:class:`Plugin```, ``:func:`~pkg.mod.f```); the site renders
them as Markdown, so each role becomes a code span (the ``~`` form keeps the last name, as
Sphinx shows it) and a paragraph's closing ``::`` (reST: "a literal block follows")
becomes ``:``. Nothing is imported: Griffe reads the sources.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|mod|data|exc|obj|const|type):`(~?)([^`]+)`")
_LITERAL = re.compile(r"(\S)::$", re.MULTILINE)


def _role(match: re.Match) -> str:
    tilde, target = match.groups()
    if tilde:
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def markdown(text: str) -> str:
    """A docstring's text with the Sphinx roles as code spans."""
    return _LITERAL.sub(r"\1:", _ROLE.sub(_role, text))


class SphinxRoles(griffe.Extension):
    """Rewrites every docstring as :func:`markdown` does, when Griffe loads it."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj.docstring.value)
