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


README = ROOT / "README.md"


def test_the_readme_stays_short_and_its_links_exist():
    """The README is the front door (issue #57): what CAVIAR is, the two commands, a picture and
    links into the site; costs and known problems live on the site's pages. mkdocs does not see
    the README, so its relative links are checked here."""
    text = README.read_text()
    n = len(text.splitlines())
    assert n <= 120, f"README.md has {n} lines (at most 120): move detail to a page under docs/"
    assert text.count("bash scripts/setup.sh && ") == 2, "the README's two commands"
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert len(targets) > 20
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, f"README.md links to {missing}, which do not exist"


def test_the_views_committed_bundle_was_built_from_the_sources_in_web():
    """python/caviar/view/static/ is committed built (scripts/setup-view.sh says why).
    BUILT-FROM.sha256 beside it, written by ``bash scripts/setup-view.sh --build``, records the
    hashes of web/'s sources and of the bundle at that build: a source edited without a
    rebuild, or a bundle edited by hand, fails here."""
    import hashlib

    static = ROOT / "python" / "caviar" / "view" / "static"
    record = static / "BUILT-FROM.sha256"
    recorded = dict(reversed(line.split("  ", 1)) for line in record.read_text().splitlines())
    sources = ["web/build.mjs", "web/package.json", "web/package-lock.json"]
    sources += [p.relative_to(ROOT).as_posix() for p in (ROOT / "web" / "src").rglob("*") if p.is_file()]
    built = [p.relative_to(ROOT).as_posix() for p in static.iterdir() if p.is_file() and p != record]
    rebuild = "rebuild and commit: bash scripts/setup-view.sh --build --no-browser"
    assert sorted(recorded) == sorted(sources + built), \
        f"{record.name} lists other files than web/ and the bundle: {rebuild}"
    stale = [p for p, digest in recorded.items() if hashlib.sha256((ROOT / p).read_bytes()).hexdigest() != digest]
    assert not stale, f"changed since the bundle was built: {stale}; {rebuild}"
