"""One adapter to Sionna RT's internals (issue #24, part 3): it checks the installed
version and every name it uses, it is the only module that touches them, and without it
the radio scene falls back to Sionna's own loop, with a warning, and finds the same links."""

import pathlib
import re
import tokenize

import numpy as np
import pytest

from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.radio import RadioConfig, RadioScene
from caviar_plugins.radio import sionna_internals as internals

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
    plain = RadioScene(RadioConfig(**cfg, shoot_cache=False), seed=3)
    plain.place(ON_ROUTE)
    ref = plain.solve()
    monkeypatch.setattr(internals, "PROBLEM", "sionna-rt 9.9.0 is installed; checked against 2.2.x only")
    with pytest.warns(RuntimeWarning, match=r"9\.9\.0.*Sionna's own shoot-and-bounce runs \(shoot_cache = true "
                                            r"ignored\).*not reported"):
        fallback = RadioScene(RadioConfig(**cfg, shoot_cache=True), seed=3)
    assert fallback.shoot_cache is None
    for shift in (0.0, 1.0, 0.0):  # the same geometry again: a cache would have served it
        fallback.place({k: p + [shift, 0, 0] for k, p in ON_ROUTE.items()})
        got = fallback.solve()
    for key in ON_ROUTE:
        assert got[key].n_paths == ref[key].n_paths > 0
        np.testing.assert_allclose(got[key].h, ref[key].h, rtol=1e-5, atol=1e-12)


def test_forced_solve_traces_again_and_keeps_its_paths():
    radio = RadioScene(RadioConfig(scene="empty", samples_per_src=1000, max_depth=1, threads=1, uav_mesh=False,
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


PRIVATE = re.compile(r"\._candidate_generator\b|\._los\b|\._shoot_and_bounce|\._sampler\b|_sample_radio_material|"
                     r"sionna\.rt\.path_solvers|PathsBuffer|SampleData|plane_hash_functions|edge_hash_functions")


def code_lines(path: pathlib.Path) -> dict[int, str]:
    """A file's code without strings, docstrings and comments, by line."""
    lines: dict[int, str] = {}
    with path.open("rb") as f:
        for tok in tokenize.tokenize(f.readline):
            if tok.type in (tokenize.NAME, tokenize.OP, tokenize.NUMBER):
                lines[tok.start[0]] = lines.get(tok.start[0], "") + (
                    tok.string if tok.type == tokenize.OP else " " + tok.string)
    return {n: re.sub(r" ?\. ?", ".", line) for n, line in lines.items()}


def test_only_the_adapter_touches_sionna_internals_and_only_the_scene_its_memo():
    offenders = []
    for path in sorted(PLUGINS.rglob("*.py")):
        if path.name == "sionna_internals.py":
            continue
        for n, code in code_lines(path).items():
            if PRIVATE.search(code) or re.search(r"radio\._|\.solver\.last\b", code):
                offenders.append(f"{path.relative_to(PLUGINS)}:{n}: {code.strip()}")
    assert not offenders, "\n".join(offenders)
