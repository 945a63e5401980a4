"""One run reader (issue #22): the core knows the run directory's layout and the
per-module totals; load_run, report and the view read through caviar.rundir; the
generic view names no domain topic and learns them from the plugins' contract."""

from __future__ import annotations

import ast
import pathlib
import re

import polars as pl
import pytest

import caviar
from caviar import _core
from caviar.rundir import RunDir
from caviar.view.contract import CORE, ViewContract, registered
from caviar.view.data import RunData
from conftest import ROOT, write_config

QUICKSTART = ROOT / "blueprints" / "quickstart" / "config.toml"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The quickstart, read half-way (parts) and at the end (compacted)."""
    tmp = tmp_path_factory.mktemp("rundir")
    sim = caviar.Simulation.from_toml(QUICKSTART, {"episode.steps": 12}, out=tmp / "run")
    for _ in range(6):
        sim.step()
    live = {t: RunDir(tmp / "run").read(t) for t in ("messages", "timings")}
    files = RunDir(tmp / "run").table_files("messages")
    sim.run()
    return tmp / "run", live, files


def test_parts_of_a_live_run_and_the_compacted_file_read_the_same(runs):
    run, live, files = runs
    assert [f.name for f in files] == [f"part-{k:06d}.parquet" for k in range(6)]
    assert all(f.parent == run / "messages" for f in files)
    d = RunDir(run)
    assert d.is_compacted("messages") and d.table_files("timings") == [run / "timings.parquet"]
    full = d.read("messages")
    assert full.filter(pl.col("step") < 6).equals(live["messages"])
    assert live["messages"]["step"].max() == 5 and full["step"].max() == 11
    assert d.read("timings").filter(pl.col("step") < 6).equals(live["timings"])
    # The view's reader sees the same messages.
    view = RunData(run)
    assert view.last_step == 11 and view.topics == set(full["topic"].unique())


def test_module_times_are_the_totals_inspect_prints(runs):
    run, _, _ = runs
    log = caviar.load_run(run)
    times = log.module_times()
    # Recomputed here from the timings table, independently of the core.
    t = log.timings
    expected = t.group_by("module", maintain_order=True).agg(
        pl.len().alias("steps"), pl.col("wall_s").sum(), pl.col("cpu_s").sum(), pl.col("rss_mib").max())
    assert times["module"].to_list()[-1] == "caviar.core"  # the core's own row, last
    assert sorted(times["module"].to_list()) == sorted(expected["module"].to_list())
    for row in expected.iter_rows(named=True):
        got = times.filter(pl.col("module") == row["module"]).row(0, named=True)
        assert got["steps"] == row["steps"]
        assert got["wall_s"] == pytest.approx(row["wall_s"], rel=1e-12)
        assert got["cpu_s"] == pytest.approx(row["cpu_s"], rel=1e-12)
        assert got["max_rss_mib"] == pytest.approx(row["rss_mib"])
        assert got["mean_wall_s"] == pytest.approx(row["wall_s"] / row["steps"])
    assert times["share"].sum() == pytest.approx(1.0)
    # inspect prints the same table, rounded.
    text = _core.inspect(run)
    lines = text.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("module "))
    printed = [line.split() for line in lines[head + 1:head + 1 + times.height]]
    assert [r[0] for r in printed] == times["module"].to_list()
    for (_name, steps, wall, share, mean_ms, cpu, rss, n_in, n_out), got in zip(
            printed, times.iter_rows(named=True), strict=True):
        assert int(steps) == got["steps"]
        assert float(wall) == pytest.approx(got["wall_s"], abs=6e-5)
        assert float(share.rstrip("%")) == pytest.approx(100 * got["share"], abs=0.06)
        assert float(mean_ms) == pytest.approx(1e3 * got["mean_wall_s"], abs=6e-4)
        assert float(cpu) == pytest.approx(got["cpu_s"], abs=6e-5)
        assert float(rss) == pytest.approx(got["max_rss_mib"], abs=0.06)
        assert (int(n_in), int(n_out)) == (got["msgs_in"], got["msgs_out"])
    # Messages in and out, GPU: the timings' per-step values added up.
    counts = t.group_by("module").agg(pl.col("msgs_in").sum(), pl.col("msgs_out").sum(),
                                      pl.col("gpu_util_pct").mean(), pl.col("gpu_mem_mib").max())
    for row in counts.iter_rows(named=True):
        got = times.filter(pl.col("module") == row["module"]).row(0, named=True)
        assert (got["msgs_in"], got["msgs_out"]) == (row["msgs_in"], row["msgs_out"])
        for mine, theirs in (("mean_gpu_util_pct", "gpu_util_pct"), ("max_gpu_mem_mib", "gpu_mem_mib")):
            if row[theirs] is None:
                assert got[mine] is None  # no GPU measured
            else:
                assert got[mine] == pytest.approx(row[theirs])


def test_a_directory_without_a_run_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        RunDir(tmp_path).table_files("messages")
    with pytest.raises(FileNotFoundError, match="no run.json"):
        caviar.load_run(tmp_path)


def test_the_view_without_a_contract_draws_no_domain_topic(runs):
    run, _, _ = runs
    bare = RunData(run, contract=CORE)
    assert bare.entities == {} and bare.radio == {} and bare.frames == {}
    assert [e["topic"] for e in bare.events] == []  # the quickstart's steps end the episode, no module does
    full = RunData(run)
    assert set(full.entities) == {"uav1"} and set(full.radio) == {"uav1"}


def test_the_plugins_contract_is_discovered_and_merged():
    c = registered()
    assert "3D.mobility.positions" in c.positions and "communications.throughput" in c.throughput
    assert "caviar.episode.end" in c.event_topics and ("ai.detections", "count") in c.event_requires
    assert c.default_scene == "central_park"
    other = ViewContract(positions=("x.pos",), default_scene="elsewhere")
    merged = c.merged(other)
    assert merged.positions[-1] == "x.pos" and merged.default_scene == "central_park"
    assert c.merged(c) == c


def test_with_no_contract_registered_the_view_shows_core_topics_only(runs, monkeypatch):
    """No package registers a contract in group caviar.view: the view still serves the
    run (steps, timings, the recorded topics' names) but draws nothing of a domain."""
    import caviar.view.contract as contract_module
    from caviar.view.server import ViewState

    asked = []
    monkeypatch.setattr(contract_module, "entry_points", lambda group: asked.append(group) or [])
    assert registered() == CORE and asked == ["caviar.view"]
    run, _, _ = runs
    state = ViewState(run)
    assert state.data.contract == CORE
    data = state.data.since(0)
    assert len(data["steps"]) == 12 and set(data["timings"]) == {"uav", "comm", "monitor", "caviar.core"}
    assert data["entities"] == {} and data["radio"] == {} and data["frames"] == {} and data["events"] == []
    info = state.run_info()
    assert info["contract"] == CORE.for_page() == {
        "positions": [], "throughput": [], "link": [], "frame_prefixes": [], "event_prefixes": [],
        "event_topics": ["caviar.episode.end"]}
    assert info["scene"]["name"] == "" and info["scene"]["xml"] is None  # no default scene, no scene folder
    assert "3D.mobility.positions" in info["topics"]  # recorded, listed, not drawn


def test_the_page_is_sent_the_plugins_contract(runs):
    from caviar.view.server import ViewState

    run, _, _ = runs
    c = registered()
    info = ViewState(run).run_info()
    assert info["contract"] == c.for_page()
    assert info["contract"]["positions"] == ["3D.mobility.positions"]
    assert info["contract"]["frame_prefixes"][0] == "3D.camera."  # camera frames shown first
    # The scene: the plugins' default, found in the scene folder their contract names.
    assert info["scene"]["name"] == "central_park" and info["scene"]["origin"].startswith("default")
    assert pathlib.Path(info["scene"]["xml"]).parent.parent in {pathlib.Path(d) for d in c.scene_dirs}
    assert info["scene"]["meshes"]


def test_the_page_names_no_domain_topic():
    """The browser page (its sources and the committed bundle) learns every domain topic
    from the contract in /api/run."""
    import caviar_plugins.schema as schema

    c = registered()
    names = {v for k, v in vars(schema).items() if k.isupper() and isinstance(v, str)}
    names |= set(c.frame_prefixes + c.event_prefixes + c.event_topics + c.positions + c.throughput + c.link)
    names -= set(CORE.event_topics)
    assert "3D.camera" in names and "mission." in names
    pattern = re.compile("|".join(rf"(?<![\w.]){re.escape(n)}(?![\w])" if not n.endswith(".") else
                                  rf"(?<![\w.]){re.escape(n)}" for n in sorted(names)))
    files = [*sorted((ROOT / "web" / "src").iterdir()), *sorted((ROOT / "python/caviar/view/static").glob("*.*"))]
    assert any(f.name == "view.js" for f in files) and any(f.name == "main.js" for f in files)
    found = [f"{f.relative_to(ROOT)}: {m.group(0)!r}" for f in files for m in pattern.finditer(f.read_text())]
    assert not found, found


def test_the_core_package_names_no_domain_topic():
    """No string in python/caviar's code (docstrings aside) is a topic of the plugins."""
    domain = re.compile(r"^(3D\.|communications\.|mission\.|ai\.|network\.)")
    found = []
    for f in sorted((ROOT / "python" / "caviar").rglob("*.py")):
        tree = ast.parse(f.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        found += [f"{f.relative_to(ROOT)}:{n.lineno}: {n.value!r}" for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
                  and domain.match(n.value)]
    assert not found, found
    assert pathlib.Path(caviar.__file__).parent == ROOT / "python" / "caviar"


def test_a_run_that_recorded_nothing_reads_as_empty_tables_with_the_recorded_columns(tmp_path, cli):
    """A run that failed in setup has no part file: its tables are empty, with the columns
    (and types) of a table that was recorded, so that selecting a topic just finds none."""
    write_config(tmp_path, """
[episode]
ts = 0.1
steps = 3
stages = ["s"]
[modules.counter]
stage = "s"
plugin = "sample_plugins:Counter"
""")
    cli("run", "exp.toml", "-q", "--out", "full")
    full = caviar.load_run(tmp_path / "full")
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    (empty_dir / "messages").mkdir()
    (empty_dir / "timings").mkdir()
    (empty_dir / "run.json").write_text((tmp_path / "full" / "run.json").read_text())
    empty = caviar.load_run(empty_dir)
    assert empty.messages.is_empty() and empty.timings.is_empty()
    assert empty.messages.schema == full.messages.schema
    assert empty.timings.schema == full.timings.schema
    assert empty.topic("count").height == 0 and empty.decoded("count") == []


def test_only_rundir_names_the_files_of_a_run_directory():
    """One owner of the run-directory format in Python (issue #40, part 3): outside
    ``caviar/rundir.py`` no code of ``python/`` or ``plugins/`` names ``run.json`` or
    ``progress.json`` (docstrings and comments may); the view, the supervisor, the SAR
    results and the exporters ask :class:`caviar.rundir.RunDir`."""
    root = pathlib.Path(__file__).resolve().parents[1]
    offenders = []
    for base in (root / "python" / "caviar", root / "plugins" / "caviar_plugins"):
        for path in sorted(base.rglob("*.py")):
            if path.name == "rundir.py" and path.parent.name == "caviar":
                continue
            tree = ast.parse(path.read_text())
            # Docstrings (of modules, classes, functions and attributes): strings standing alone.
            docstrings = {id(node.value) for node in ast.walk(tree)
                          if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)}
            for node in ast.walk(tree):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings \
                        and ("run.json" in node.value or "progress.json" in node.value):
                    offenders.append(f"{path.relative_to(root)}:{node.lineno}: {node.value[:60]!r}")
    assert not offenders, "\n".join(offenders)
