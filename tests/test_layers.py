"""The plugins' layers, read from the sources (issue #57): offline tools live in
``caviar_plugins/tools/`` above the runtime packages. A runtime package (every module of
``caviar_plugins`` outside ``tools/``) imports no tool, parses no command line (argparse)
and has no ``__main__``: its modules are what a simulation loads. Pure ``ast``, nothing is
imported."""

from __future__ import annotations

import ast
import pathlib

PLUGINS = pathlib.Path(__file__).resolve().parents[1] / "plugins"
PACKAGE = PLUGINS / "caviar_plugins"
TOOLS = PACKAGE / "tools"


def runtime_modules() -> list[pathlib.Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if TOOLS not in p.parents)


def _module_name(path: pathlib.Path, root: pathlib.Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: pathlib.Path, root: pathlib.Path = PLUGINS) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path`` (a module under ``root``),
    relative ones resolved; ``from a import b`` gives both ``a`` and ``a.b`` (``b`` may be a
    module)."""
    package = _module_name(path, root).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package[:len(package) - node.level + 1], *([base] if base else [])])
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def _is_main_guard(node: ast.AST) -> bool:
    """``if __name__ == "__main__":``."""
    if not (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)):
        return False
    sides = [node.test.left, *node.test.comparators]
    return any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides) and \
        any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides)


def layer_problems(path: pathlib.Path, root: pathlib.Path = PLUGINS) -> list[str]:
    """What makes ``path`` (a runtime module under ``root``) break the layers: one line per
    offending statement, in the file's order."""
    where = path.relative_to(root)
    found: dict[int, str] = {}
    for line, name in imported_modules(path, root):
        if name == "caviar_plugins.tools" or name.startswith("caviar_plugins.tools."):
            found.setdefault(line, f"imports {name}")
        elif name.split(".")[0] == "argparse":
            found.setdefault(line, "uses argparse (a command line: it belongs in caviar_plugins/tools)")
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if _is_main_guard(node):
            found.setdefault(node.lineno, "if __name__ == '__main__' (a command: it belongs in caviar_plugins/tools)")
    problems = [f"{where}:{line}: {what}" for line, what in sorted(found.items())]
    if path.name == "__main__.py":
        problems.append(f"{where}: a __main__ (a command: it belongs in caviar_plugins/tools)")
    return problems


def test_no_runtime_package_imports_a_tool_or_parses_a_command_line():
    modules = runtime_modules()
    assert len(modules) > 50 and PACKAGE / "radio" / "sionna_link.py" in modules
    assert not any(TOOLS in p.parents for p in modules)
    problems = [line for path in modules for line in layer_problems(path)]
    assert not problems, "\n".join(problems)


def test_the_tools_are_packages_of_the_plugins_and_hold_the_commands():
    packages = [p for p in TOOLS.rglob("*") if p.is_dir() and p.name != "__pycache__"]
    assert {p.name for p in packages} >= {"export", "scene", "calibration", "training", "baselines", "results"}
    assert (TOOLS / "__init__.py").exists() and all((p / "__init__.py").exists() for p in packages)
    # The commands are here: what the guard would refuse in a runtime package.
    commands = [p for p in TOOLS.rglob("*.py") if any(name == "argparse" for _, name in imported_modules(p))]
    assert len(commands) >= 10, commands


def test_the_guard_sees_every_way_in(tmp_path):
    pkg = tmp_path / "caviar_plugins" / "radio"
    pkg.mkdir(parents=True)
    bad = pkg / "bad.py"
    bad.write_text("import caviar_plugins.tools.export.cli\n"
                   "from caviar_plugins import tools\n"
                   "from ..tools.calibration import main\n"
                   "from argparse import ArgumentParser\n"
                   "def f():\n    import argparse\n"
                   "if '__main__' == __name__:\n    f()\n")
    problems = layer_problems(bad, tmp_path)
    assert [p.split(": ", 1)[0] for p in problems] == [f"caviar_plugins/radio/bad.py:{n}" for n in (1, 2, 3, 4, 6, 7)]
    assert "imports caviar_plugins.tools.calibration" in problems[2]
    fine = pkg / "fine.py"
    fine.write_text("from caviar_plugins.radio import beams\nfrom . import link_budget\n"
                    "# python -m caviar_plugins.tools.training.train_tree, if __name__ == '__main__'\n")
    assert layer_problems(fine, tmp_path) == []
    main = pkg / "__main__.py"
    main.write_text("")
    assert layer_problems(main, tmp_path) == ["caviar_plugins/radio/__main__.py: a __main__ (a command: it belongs in "
                                    "caviar_plugins/tools)"]
