"""The documentation site is true to the code where a test can tell (issue #40, part 4):
the architecture page names every module of the Rust core, of the Python package and every
subpackage of the plugins, and the command-line reference is what the installed
``caviar-core`` prints. (``scripts/test.sh`` builds the whole site with warnings as errors;
the build fails on a page that names a repository path that does not exist.)"""

import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
ARCHITECTURE = (ROOT / "docs" / "architecture.md").read_text()


def test_the_architecture_page_names_every_rust_module():
    lib = (ROOT / "crates" / "caviar-core" / "src" / "lib.rs").read_text()
    modules = re.findall(r"^(?:pub )?mod (\w+);", lib, re.M)
    assert len(modules) > 10
    missing = [m for m in modules if not re.search(rf"\b{m}\b", ARCHITECTURE)]
    assert not missing, f"docs/architecture.md does not name the core's modules {missing}"


def test_the_architecture_page_names_every_python_module_and_plugin_subpackage():
    python = [p.stem for p in (ROOT / "python" / "caviar").glob("*.py") if p.stem != "__init__"]
    python += [p.name for p in (ROOT / "python" / "caviar").iterdir() if (p / "__init__.py").exists()]
    plugins = [p.name for p in (ROOT / "plugins" / "caviar_plugins").iterdir() if (p / "__init__.py").exists()]
    missing = [m for m in python if not re.search(rf"\b{re.escape(m)}(\.py|/)", ARCHITECTURE)]
    missing += [f"caviar_plugins/{m}" for m in plugins if f"{m}/" not in ARCHITECTURE]
    assert not missing, f"docs/architecture.md does not name {missing}"


def test_the_command_line_reference_is_what_caviar_core_prints():
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "docs_cli.py"), "--check"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, f"docs/reference/cli.md is stale: run scripts/docs_cli.py\n{p.stdout}{p.stderr}"


def test_the_plugins_package_lists_and_gives_every_plugin_it_registers():
    import tomllib

    import caviar_plugins

    entry_points = tomllib.loads((ROOT / "plugins" / "pyproject.toml").read_text())["project"]["entry-points"]
    registered = entry_points["caviar.plugins"]
    assert len(registered) >= 15
    for name, target in registered.items():
        module, cls = target.split(":")
        assert f"``{name}`` (:class:`{cls}`)" in " ".join((caviar_plugins.__doc__ or "").split()), name
        assert cls in caviar_plugins.__all__ and getattr(caviar_plugins, cls).__module__ == module, name


def test_no_source_file_is_over_600_lines():
    """A file a person reads in one sitting (issue #40): the bundled page (view.js, built by
    web/build.mjs from web/src) is the only generated source, and is left out."""
    roots = ["python", "plugins", "crates", "web/src", "tests", "benches", "scripts", "blueprints", "examples"]
    long = []
    for root in roots:
        for path in (ROOT / root).rglob("*"):
            if path.suffix in (".py", ".rs", ".js", ".mjs", ".sh") and "node_modules" not in path.parts \
                    and path.name != "view.js" and path.is_file():
                n = len(path.read_text(errors="replace").splitlines())
                if n > 600:
                    long.append(f"{path.relative_to(ROOT)}: {n} lines")
    assert not long, "\n".join(long)
