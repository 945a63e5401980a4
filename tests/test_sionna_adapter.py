"""Two adapters to Sionna RT's and Sionna SYS's internals (issue #24 part 3, #40 part 1): one
checks the installed version and every name it uses, they are the only modules that touch
them (an allowlist guard), and without it the radio scene falls back to Sionna's own loop,
with a warning, and finds the same links. The plugins' imports have no circle."""

import ast
import pathlib
import re

import numpy as np
import pytest

from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.radio import RadioConfig, RadioScene, sionna_sys_adapter
from caviar_plugins.rt import sionna_adapter as internals
from caviar_plugins.rt.settings import with_raytracing

PLUGINS = pathlib.Path(__file__).resolve().parents[1] / "plugins" / "caviar_plugins"
RECEIVERS = {"a": np.array([30.0, 5.0, 10.0]), "b": np.array([-40.0, 5.0, 12.0])}  # free space
ROUTE = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
ON_ROUTE = {"a": ROUTE.at(0.0), "b": ROUTE.at(60.0)}  # the SAR flight


def test_the_installed_sionna_rt_is_the_one_the_adapter_was_written_for():
    import sionna.rt

    assert internals.PROBLEM is None
    assert tuple(int(x) for x in sionna.rt.__version__.split(".")[:2]) == internals.TESTED_VERSION
    pin = (PLUGINS.parent / "pyproject.toml").read_text()
    major, minor = internals.TESTED_VERSION
    assert f'"sionna-rt>={major}.{minor},<{major}.{minor + 1}"' in pin


@pytest.mark.parametrize("version", ["2.3.0", "3.0.1", "2.1.9", "dev"])
def test_another_version_is_refused_naming_both(monkeypatch, version):
    import sionna.rt

    monkeypatch.setattr(sionna.rt, "__version__", version)
    problem = internals._check()
    assert problem is not None and f"sionna-rt {version} is installed" in problem and "2.2.x" in problem


@pytest.mark.parametrize("cls, name", [("SBCandidateGenerator", "_sample_radio_material"),
                                       ("SBCandidateGenerator", "_los"),
                                       ("PathsBuffer", "add_paths")])
def test_a_missing_internal_is_named(monkeypatch, cls, name):
    from sionna.rt.path_solvers.paths_buffer import PathsBuffer
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    monkeypatch.delattr({"SBCandidateGenerator": SBCandidateGenerator, "PathsBuffer": PathsBuffer}[cls], name)
    problem = internals._check()
    assert problem is not None and f"{cls}.{name}" in problem


def test_a_reordered_argument_is_caught(monkeypatch):
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    def los(self, mi_scene, src_positions, tgt_positions, paths_counter_per_source, paths, src_boxes=None):
        raise AssertionError("not called")

    monkeypatch.setattr(SBCandidateGenerator, "_los", los)
    problem = internals._check()
    assert problem is not None and "_los" in problem and "'paths_counter_per_source'" in problem
    with monkeypatch.context() as m:
        m.setattr(internals, "PROBLEM", problem)
        with pytest.raises(internals.SionnaInternalsError, match="_los"):
            internals.require()


def test_without_the_internals_the_scene_warns_and_sionnas_loop_finds_the_same_links(monkeypatch):
    cfg = dict(scene="central_park", samples_per_src=20_000, max_depth=2, threads=1, uav_mesh=False)
    plain = RadioScene(with_raytracing(RadioConfig, **cfg, shoot_cache=False), seed=3)
    plain.place(ON_ROUTE)
    ref = plain.solve()
    monkeypatch.setattr(internals, "PROBLEM", "sionna-rt 9.9.0 is installed; checked against 2.2.x only")
    with pytest.warns(RuntimeWarning, match=r"9\.9\.0.*Sionna's own shoot-and-bounce runs \(shoot_cache = true "
                                            r"ignored\).*not reported"):
        fallback = RadioScene(with_raytracing(RadioConfig, **cfg, shoot_cache=True), seed=3)
    assert fallback.shoot_cache is None
    for shift in (0.0, 1.0, 0.0):  # the same geometry again: a cache would have served it
        fallback.place({k: p + [shift, 0, 0] for k, p in ON_ROUTE.items()})
        got = fallback.solve()
    for key in ON_ROUTE:
        assert got[key].n_paths == ref[key].n_paths > 0
        np.testing.assert_allclose(got[key].h, ref[key].h, rtol=1e-5, atol=1e-12)


def test_forced_solve_traces_again_and_keeps_its_paths():
    radio = RadioScene(with_raytracing(RadioConfig, scene="empty", samples_per_src=1000, max_depth=1, threads=1,
                                       uav_mesh=False,
                                   shoot_cache=False), seed=1)
    assert radio.last_paths is None
    radio.place(RECEIVERS)
    first = radio.solve()
    paths = radio.last_paths
    assert paths is not None and np.array(paths.valid).sum() == len(RECEIVERS)  # the two LOS paths
    assert radio.solve() is first and radio.last_paths is paths  # nothing moved: reused
    again = radio.solve(force=True)
    assert again is not first and radio.last_paths is not paths
    for key in RECEIVERS:
        np.testing.assert_array_equal(again[key].h, first[key].h)


SOURCES = [PLUGINS, PLUGINS.parents[1] / "python" / "caviar"]
ADAPTERS = (PLUGINS / "rt" / "sionna_adapter.py", PLUGINS / "radio" / "sionna_sys_adapter.py")
OWN_PRIVATE = {
    "_assign": "plugins/caviar_plugins/rt/scatterers.py",  # ScattererPool's, for update_pools
    "_stage": "plugins/caviar_plugins/rt/scatterers.py",
    "_from_wire": "python/caviar/plugin.py",  # Message's
    "_kind": "python/caviar/plugin.py",
    "_raw": "python/caviar/plugin.py",
    "_libsumo_in_use": "plugins/caviar_plugins/traffic/sumo.py",  # Sumo's
}
"""The only private names (``obj._name``, obj not ``self`` or ``cls``) used outside the
adapters: this project's own, each defined in the file named (checked)."""
# (sionna.phy.channel.tr38901 is where Sionna documents its 38.901 models: UMa, UMaScenario, LSPGenerator.)
PUBLIC_SIONNA = {"sionna", "sionna.rt", "sionna.sys", "sionna.phy", "sionna.phy.channel.tr38901"}
"""The Sionna modules imported outside the adapters: the documented packages' top level."""


def python_files():
    for root in SOURCES:
        for path in sorted(root.rglob("*.py")):
            if path not in ADAPTERS:
                yield path


def private_uses(path: pathlib.Path) -> list[tuple[int, str, str]]:
    """(line, name, code) of every ``obj._name`` in a file whose ``obj`` is not ``self``/``cls``,
    and of every Sionna module or private name imported."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                found.append((node.lineno, node.attr, ast.unparse(node)))
        modules = []
        if isinstance(node, ast.Import):
            modules = [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            modules = [(node.module, a.name) for a in node.names]
        for module, name in modules:
            if module.split(".")[0] != "sionna":
                continue
            if module not in PUBLIC_SIONNA:
                found.append((node.lineno, module, f"import of {module}"))
            elif name is not None and name.startswith("_"):
                found.append((node.lineno, name, f"from {module} import {name}"))
    return found


def test_only_the_adapter_uses_private_names_of_sionna():
    """An allowlist: outside ``rt/sionna_adapter.py`` and ``radio/sionna_sys_adapter.py``, no file
    reaches into another object's private names but this project's own listed in :data:`OWN_PRIVATE`, and Sionna is
    imported from its documented packages only (Sionna RT's and Sionna SYS's internals
    alike: ``olla._offset`` or ``sionna.rt.path_solvers`` anywhere else fails)."""
    offenders = [f"{path.relative_to(PLUGINS.parents[1])}:{line}: {code}"
                 for path in python_files() for line, name, code in private_uses(path) if name not in OWN_PRIVATE]
    assert not offenders, "\n".join(offenders)


def test_the_allowed_private_names_are_this_projects_own():
    for name, file in OWN_PRIVATE.items():
        text = (PLUGINS.parents[1] / file).read_text()
        assert re.search(rf"^\s*(def {name}\(|self\.{name}\b.*=|{name}\b.*=)", text, re.M), (name, file)


def test_the_guard_sees_a_private_name_of_sionna_sys(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f(olla):\n    olla._offset[:, 0] = 0.0\n\nfrom sionna.rt.path_solvers import paths_buffer\n")
    assert sorted(name for _, name, _ in private_uses(bad)) == ["_offset", "sionna.rt.path_solvers"]


def module_graph() -> dict[str, set[str]]:
    """The plugins' modules and what each imports of them, at module level or in a function."""
    root = PLUGINS.parent
    names = {}
    for path in PLUGINS.rglob("*.py"):
        parts = list(path.relative_to(root).with_suffix("").parts)
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in names.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names if a.name in names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    edges.add(full if full in names else node.module)
        # Importing a.b.c runs the packages a.b first (their __init__ re-exports): edges to them
        # too, but to the root package, which every import runs before anything else.
        edges |= {".".join(e.split(".")[:i]) for e in list(edges) for i in range(2, e.count(".") + 1)}
        graph[name] = {e for e in edges if e in names and e != name and not name.startswith(e + ".")}
    return graph


def test_the_plugins_imports_have_no_circle():
    """No module of the plugins imports, directly or through others, a module that imports
    it (function-level imports count: a circle broken by a late import is still one; so do
    the packages whose ``__init__`` an import runs)."""
    graph = module_graph()
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> None:
        if node in path:
            raise AssertionError("import circle: " + " -> ".join(path[path.index(node):] + [node]))
        if node in done:
            return
        for nxt in sorted(graph[node]):
            visit(nxt, path + [node])
        done.add(node)

    for node in sorted(graph):
        visit(node, [])
    assert "caviar_plugins.rt.shoot_cache" in graph["caviar_plugins.rt.solver"]


def test_the_link_levels_phy_abstraction_finds_grid_indices_as_sionnas_own():
    """The link level's PHY abstraction takes the interpolation grids' lengths from their
    (min, max, delta) rather than ``len`` of the numpy grids (which a compiled group made tensor
    inputs, converted and guarded at every call): the lengths numpy's grids have, and the indices
    Sionna's own ``get_idx_from_grid`` gives, exactly, on and off the grids and past their ends."""
    import sionna.sys
    import torch

    phy = sionna_sys_adapter.phy_abstraction("cpu", sionna_sys_adapter.own_generator(torch.device("cpu"), 0))
    rng = np.random.default_rng(5)
    for which, grid, (lo, hi, delta) in (("snr", phy._snr_dbs_interp, phy._snr_db_interp_min_max_delta),
                                         ("cbs", phy._cbs_interp, phy._cbs_interp_min_max_delta)):
        values = torch.tensor(np.concatenate([grid, grid + delta / 2, rng.uniform(lo - 5 * delta, hi + 5 * delta, 500),
                                              [lo - 1e6, hi + 1e6]]))
        got = phy.get_idx_from_grid(values, which)
        want = sionna.sys.PHYAbstraction.get_idx_from_grid(phy, values, which)
        assert torch.equal(got, want), which
        assert int(got.max()) == len(grid) - 1 and int(got.min()) == 0
