"""A standing corpus of malformed configurations (issue #13).

Every case is generated from one good, quickstart-like base config. Each one must be
refused by ``caviar-core validate`` and ``caviar-core run`` with exit status 2 and a
one-line message naming the file (and the line and the key where they exist), with no
traceback, and ``run`` must not create a run directory (or anything else).

``validate`` and ``run`` are driven in-process through ``caviar._core.main`` (the same
code as the console script, without an interpreter start per case); a representative
subset also goes through the installed ``caviar-core`` script.
"""

from __future__ import annotations

import pathlib
import re
import subprocess

import pytest

from caviar import _core
from configs import caviar_core, caviar_env

BASE = """\
[episode]
ts = 0.1
steps = 3
seed = 1
stages = ["mobility", "communications", "ai"]

[output]
name = "bad"
dir = "runs"

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
[modules.uav.params]
speed = 5.0
ue_id = "uav1"

[modules.comm]
stage = "communications"
plugin = "free-space-link"
[modules.comm.params]
tx_position = [-154.0, 64.0, 120.0]
frequency_hz = 40e9

[modules.monitor]
stage = "ai"
plugin = "link-monitor"
[modules.monitor.params]
plot = false
"""

NATS = '[transport]\nkind = "nats"\n'


class Case:
    """A malformed config: its text, the key its message must name (None: there is
    none, e.g. a syntax error) and a snippet whose line the message must give (None:
    no line, e.g. a missing key)."""

    def __init__(self, id: str, text: str, key: str | None, at: str | None):
        self.id, self.text, self.key, self.at = id, text, key, at

    def line(self) -> int | None:
        if self.at is None:
            return None
        i = self.text.index(self.at)
        return self.text.count("\n", 0, i) + 1


def rep(old: str, new: str, base: str = BASE) -> str:
    assert base.count(old) == 1, old
    return base.replace(old, new)


def after(header: str, line: str, base: str = BASE) -> str:
    """``line`` inserted right after the line ``header``."""
    return rep(header + "\n", header + "\n" + line + "\n", base)


CASES: list[Case] = []


def make_case(id: str, text: str, key: str | None, at: str | None = "") -> Case:
    """``at=""``: the snippet is the value of the last component of ``key`` as written
    (the first line that mentions it); None: no line expected. (tests/test_bad_input_corpus.py
    builds its cases with it too.)"""
    if at == "":
        at = None
        if key is not None:
            name = key.split(".")[-1]
            m = re.search(rf"^(?:{re.escape(name)}\s*=|\[[^\]]*\b{re.escape(name)}\])", text, re.M)
            at = m.group(0) if m else None
    return Case(id, text, key, at)


def case(id: str, text: str, key: str | None, at: str | None = "") -> None:
    CASES.append(make_case(id, text, key, at))


# --- syntax errors -------------------------------------------------------------------
case("syntax-open-array", rep('stages = ["mobility", "communications", "ai"]', 'stages = ["mobility"'), None,
     None)
case("syntax-unterminated-string", rep('plugin = "waypoint-flight"', 'plugin = "waypoint-flight'), None,
     'plugin = "waypoint-flight\n')
case("syntax-duplicate-key", rep("ts = 0.1\n", "ts = 0.1\nts = 0.2\n"), None, "ts = 0.2")
case("syntax-duplicate-module", BASE + '\n[modules.uav]\nstage = "ai"\nplugin = "link-monitor"\n', None,
     '[modules.uav]\nstage = "ai"')
case("syntax-missing-value", rep("seed = 1", "seed ="), None, "seed =")
case("syntax-bad-escape", rep('ue_id = "uav1"', 'ue_id = "uav\\q"'), None, 'ue_id = "uav\\q"')
case("syntax-garbage-line", rep("seed = 1\n", "seed = 1\nthis is not toml\n"), None, "this is not toml")
case("syntax-open-header", rep("[output]", "[output"), None, "[output")
case("syntax-int-overflow", rep("steps = 3", "steps = 99999999999999999999"), None, "steps = 9")
case("syntax-bare-word", rep('name = "bad"', "name = bad"), None, "name = bad")
case("syntax-empty-file", "", "episode", None)
case("syntax-only-comment", "# nothing here\n", "episode", None)
case("syntax-not-utf8", "[episode]\nts = 0.1 \udcff\n", None, None)
case("syntax-array-of-modules", rep("[modules.monitor]", "[[modules]]").split("[[modules]]")[0]
     + '[[modules]]\nstage = "ai"\n', None, "[[modules]]")
case("syntax-inline-redefined", rep("[modules.uav.params]", "params = {}\n[modules.uav.params]"), None,
     "[modules.uav.params]")

# --- unknown keys at every level -------------------------------------------------------
case("unknown-top", "extra = 1\n" + BASE, "extra")
case("unknown-top-table", BASE + "[extras]\nx = 1\n", "extras")
case("unknown-episode", after("[episode]", "tss = 0.1"), "episode.tss")
case("unknown-episode-table", BASE + "[episode.more]\nx = 1\n", "episode.more")
case("unknown-output", after("[output]", "nam = 'x'"), "output.nam")
case("unknown-transport", BASE + "[transport]\nknd = 'nats'\n", "transport.knd")
case("unknown-transport-nats", BASE + NATS + "[transport.nats]\nstep_timout = 3\n",
     "transport.nats.step_timout")
case("unknown-module-key", after("[modules.uav]", "stag = 'mobility'"), "modules.uav.stag")
case("unknown-param-uav", after("[modules.uav.params]", "sped = 5.0"), "modules.uav.params.sped")
case("unknown-param-comm", after("[modules.comm.params]", "freq = 1.0"), "modules.comm.params.freq")
case("unknown-param-monitor", after("[modules.monitor.params]", "plott = true"), "modules.monitor.params.plott")
case("unknown-module-subtable", BASE + "[modules.uav.extra]\nx = 1\n", "modules.uav.extra")

# --- missing keys -------------------------------------------------------------------------
case("missing-ts", rep("ts = 0.1\n", ""), "episode.ts", "[episode]")
case("missing-stages", rep('stages = ["mobility", "communications", "ai"]\n', ""), "episode.stages", "[episode]")
case("missing-modules", BASE.split("[modules.uav]")[0], "modules", None)
case("missing-stage", rep('stage = "mobility"\n', ""), "modules.uav.stage", "[modules.uav]")
case("missing-plugin", rep('plugin = "link-monitor"\n', ""), "modules.monitor.plugin", "[modules.monitor]")

# --- wrong types ----------------------------------------------------------------------------
for k, old, new in [
    ("episode.ts", "ts = 0.1", 'ts = "fast"'),
    ("episode.ts", "ts = 0.1", "ts = true"),
    ("episode.ts", "ts = 0.1", "ts = [0.1]"),
    ("episode.steps", "steps = 3", "steps = 2.5"),
    ("episode.steps", "steps = 3", 'steps = "3"'),
    ("episode.steps", "steps = 3", "steps = -1"),
    ("episode.seed", "seed = 1", "seed = -1"),
    ("episode.seed", "seed = 1", "seed = 1.5"),
    ("episode.seed", "seed = 1", 'seed = "x"'),
    ("episode.stages", 'stages = ["mobility", "communications", "ai"]', 'stages = "mobility"'),
    ("episode.stages", 'stages = ["mobility", "communications", "ai"]', "stages = [1, 2]"),
    ("output.dir", 'dir = "runs"', "dir = 5"),
    ("output.name", 'name = "bad"', "name = 5"),
    ("output.exclude", 'name = "bad"', 'name = "bad"\nexclude = "x.>"'),
    ("output.flush_interval", 'name = "bad"', 'name = "bad"\nflush_interval = "often"'),
    ("modules.uav.stage", 'stage = "mobility"', "stage = 3"),
    ("modules.uav.plugin", 'plugin = "waypoint-flight"', "plugin = 3"),
    ("modules.uav.every", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nevery = "1"'),
    ("modules.uav.every", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nevery = 1.5'),
    ("modules.uav.offset", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\noffset = -1'),
    ("modules.uav.subscribe", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nsubscribe = "x"'),
    ("modules.uav.subscribe", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nsubscribe = [1]'),
    ("modules.uav.params.speed", "speed = 5.0", 'speed = "fast"'),
    ("modules.uav.params.speed", "speed = 5.0", "speed = true"),
    ("modules.uav.params.ue_id", 'ue_id = "uav1"', "ue_id = 3"),
    ("modules.uav.params.end_at_last", 'ue_id = "uav1"', 'ue_id = "uav1"\nend_at_last = "yes"'),
    ("modules.comm.params.tx_position", "tx_position = [-154.0, 64.0, 120.0]", 'tx_position = "up"'),
    ("modules.comm.params.tx_position", "tx_position = [-154.0, 64.0, 120.0]", 'tx_position = ["a", "b", "c"]'),
    ("modules.comm.params.tx_position", "tx_position = [-154.0, 64.0, 120.0]", "tx_position = [1.0, 2.0]"),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", 'frequency_hz = "40GHz"'),
    ("modules.comm.params.tx_array", "frequency_hz = 40e9", "frequency_hz = 40e9\ntx_array = [8.5, 8]"),
    ("modules.monitor.params.plot", "plot = false", "plot = 1"),
    ("modules.uav.params.ue_id", 'ue_id = "uav1"', "ue_id = 1979-05-27T07:32:00Z"),
    ("episode.seed", "seed = 1", "seed = 1979-05-27"),
]:
    case(f"type-{k}-{new.split(chr(10))[-1].split('=', 1)[1].strip()[:16]}", rep(old, new), k, new.split("\n")[-1])
case("type-transport", "transport = 5\n" + BASE, "transport")
case("type-transport-kind", BASE + "[transport]\nkind = 3\n", "transport.kind")
case("type-transport-kind-unknown", BASE + "[transport]\nkind = \"carrier-pigeon\"\n", "transport.kind")
case("type-output", 'output = "x"\n' + rep("[output]\nname = \"bad\"\ndir = \"runs\"\n", ""), "output")
case("type-modules", "modules = 3\n" + BASE.split("[modules.uav]")[0], "modules", "modules = 3")
case("type-module", BASE + "[modules.x]\n", "modules.x", None)
case("type-module-value", rep("[modules.monitor]\nstage", "[modules.other]\nmonitor = 3\n[modules.monitor]\nstage"),
     "modules.other", None)
case("type-params", rep('plugin = "link-monitor"\n[modules.monitor.params]\nplot = false\n',
                        'plugin = "link-monitor"\nparams = 5\n'), "modules.monitor.params", "params = 5")

# --- NaN and infinities ---------------------------------------------------------------------
for k, old, new in [
    ("episode.ts", "ts = 0.1", "ts = nan"),
    ("episode.ts", "ts = 0.1", "ts = inf"),
    ("episode.ts", "ts = 0.1", "ts = -inf"),
    ("episode.duration", "steps = 3", "duration = nan"),
    ("episode.duration", "steps = 3", "duration = inf"),
    ("output.flush_interval", 'name = "bad"', 'name = "bad"\nflush_interval = nan'),
    ("output.flush_interval", 'name = "bad"', 'name = "bad"\nflush_interval = inf'),
    ("modules.uav.params.speed", "speed = 5.0", "speed = nan"),
    ("modules.uav.params.speed", "speed = 5.0", "speed = inf"),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", "frequency_hz = nan"),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", "frequency_hz = +inf"),
    ("modules.comm.params.tx_position", "tx_position = [-154.0, 64.0, 120.0]", "tx_position = [nan, 0.0, 0.0]"),
    ("modules.comm.params.tx_power_w", "frequency_hz = 40e9", "frequency_hz = 40e9\ntx_power_w = -inf"),
]:
    case(f"nonfinite-{k}-{new.split(chr(10))[-1].split('=')[-1].strip()}", rep(old, new), k, new.split("\n")[-1])
case("nonfinite-nats-step_timeout", BASE + NATS + "[transport.nats]\nstep_timeout = nan\n",
     "transport.nats.step_timeout")

# --- out of range -------------------------------------------------------------------------------
for k, old, new in [
    ("episode.ts", "ts = 0.1", "ts = 0"),
    ("episode.ts", "ts = 0.1", "ts = 0.0"),
    ("episode.ts", "ts = 0.1", "ts = -0.1"),
    ("episode.duration", "steps = 3", "duration = 0.0"),
    ("episode.duration", "steps = 3", "duration = -1.0"),
    ("episode.steps", "steps = 3", "steps = 0"),
    ("episode.duration", "steps = 3", "steps = 3\nduration = 1.0"),
    ("episode.duration", "ts = 0.1\nsteps = 3", "ts = 1e-300\nduration = 1.0"),
    ("episode.duration", "ts = 0.1\nsteps = 3", "ts = 1e-6\nduration = 1e300"),
    ("episode.ts", "ts = 0.1", "ts = 1e308"),
    ("episode.steps", "steps = 3", "steps = 9223372036854775807"),
    ("modules.uav.every", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nevery = 0'),
    ("modules.uav.offset", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\noffset = 1'),
    ("modules.uav.shards", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nshards = 0'),
    ("modules.uav.shards", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nshards = 2'),
    ("modules.uav.workers", 'plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nworkers = 1'),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", "frequency_hz = 0"),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", "frequency_hz = 0.0"),
    ("modules.comm.params.frequency_hz", "frequency_hz = 40e9", "frequency_hz = -1.0"),
    ("modules.uav.params.speed", "speed = 5.0", "speed = 0.0"),
    ("modules.uav.params.speed", "speed = 5.0", "speed = -5.0"),
    ("modules.uav.params.frame", 'ue_id = "uav1"', 'ue_id = "uav1"\nframe = "ecef"'),
]:
    case(f"range-{new.replace(chr(10), ', ')}", rep(old, new), k, new.split("\n")[-1])
for k in ("step_timeout", "startup_timeout", "heartbeat_timeout", "reconnect_timeout"):
    case(f"range-nats-{k}", BASE + NATS + f"[transport.nats]\n{k} = 0\n", f"transport.nats.{k}")
case("range-nats-run_id", BASE + NATS + '[transport.nats]\nrun_id = "a.b"\n', "transport.nats.run_id")
case("range-nats-spawn-and-url", BASE + NATS + '[transport.nats]\nspawn = true\nurl = "nats://127.0.0.1:1"\n',
     "transport.nats.spawn")
for k in ("server", "credentials", "tls_ca"):
    case(f"path-nats-{k}", BASE + NATS + f'[transport.nats]\n{k} = "no/such-{k}"\n', f"transport.nats.{k}")
case("range-nats-tls-half", BASE + NATS + '[transport.nats]\ntls_cert = "c.pem"\n', "transport.nats.tls_cert")

# --- bad paths ------------------------------------------------------------------------------------
case("path-waypoints-missing", rep('ue_id = "uav1"', 'ue_id = "uav1"\nwaypoints = "no-such.csv"'),
     "modules.uav.params.waypoints", 'waypoints = "no-such.csv"')
case("path-waypoints-dir", rep('ue_id = "uav1"', 'ue_id = "uav1"\nwaypoints = "."'),
     "modules.uav.params.waypoints", 'waypoints = "."')
for new in ('name = "../escaped"', 'name = "a/b"', 'name = ""', 'name = "."', 'name = ".."',
            'name = "/abs"'):
    case(f"path-output-{new}", rep('name = "bad"', new), "output.name", new)
case("path-output-dir-proc", rep('dir = "runs"', 'dir = "/proc/caviar-no/runs"'), "output.dir",
     'dir = "/proc/caviar-no/runs"')
case("path-output-dir-is-file", rep('dir = "runs"', 'dir = "cfg.toml"'), "output.dir", 'dir = "cfg.toml"')

# --- plugins --------------------------------------------------------------------------------------
for new in ('plugin = "no.such.module:X"', 'plugin = "no-such-entry-point"', 'plugin = "sample_plugins:NotAPlugin"',
            'plugin = ""', 'plugin = "   "', 'plugin = "caviar_plugins.mobility:Nope"',
            'plugin = "sample_plugins:BadPublishes"'):
    case(f"plugin-{new}", rep('plugin = "link-monitor"', new), "modules.monitor.plugin", new)

# --- bad topics -----------------------------------------------------------------------------------
for pat in ("a..b", "a.>.b", "", "a b", "*x", ">x", "a.", ".a"):
    case(f"topic-subscribe-{pat!r}", rep('plugin = "link-monitor"', f'plugin = "link-monitor"\nsubscribe = ["{pat}"]'),
         "modules.monitor.subscribe", f'subscribe = ["{pat}"]')
for pat in ("a..b", "x.>.y", ""):
    case(f"topic-exclude-{pat!r}", rep('name = "bad"', f'name = "bad"\nexclude = ["{pat}"]'), "output.exclude",
         f'exclude = ["{pat}"]')
case("topic-mirror", BASE + NATS + '[transport.nats]\nmirror = ["a..b"]\n', "transport.nats.mirror")

# --- module names, stages ----------------------------------------------------------------------
case("module-name-dot", BASE + '[modules."a.b"]\nstage = "ai"\nplugin = "link-monitor"\n', 'modules.a.b', None)
case("module-name-space", BASE + '[modules."a b"]\nstage = "ai"\nplugin = "link-monitor"\n', "modules.a b",
     '[modules."a b"]')
case("module-name-empty", BASE + '[modules.""]\nstage = "ai"\nplugin = "link-monitor"\n', "modules.", None)
case("stage-unknown", rep('stage = "ai"', 'stage = "nowhere"'), "modules.monitor.stage", 'stage = "nowhere"')
case("stage-empty", rep('stage = "ai"', 'stage = ""'), "modules.monitor.stage", 'stage = ""')
case("stages-duplicate", rep('stages = ["mobility", "communications", "ai"]',
                             'stages = ["mobility", "communications", "ai", "ai"]'), "episode.stages")
case("stages-empty", rep('stages = ["mobility", "communications", "ai"]', "stages = []"), "episode.stages")
case("stages-empty-name", rep('stages = ["mobility", "communications", "ai"]',
                              'stages = ["mobility", "communications", "ai", ""]'), "episode.stages")
case("modules-empty", BASE.split("[modules.uav]")[0] + "[modules]\n", "modules", None)

IDS = [c.id for c in CASES]
assert len(set(IDS)) == len(IDS), [i for i in IDS if IDS.count(i) > 1]


def test_the_corpus_is_large():
    assert len(CASES) >= 100, len(CASES)


def _listing(root: pathlib.Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _check_message(c: Case, path: pathlib.Path, err: str, out: str) -> None:
    where = f"{c.id}:\nstdout: {out}\nstderr: {err}"
    assert "Traceback" not in err + out, where
    assert err.startswith("error: "), where
    first = err.splitlines()[0]
    assert str(path) in first, where
    line = c.line()
    if line is not None:
        assert f"{path}:{line}:" in first, f"expected line {line}; " + where
    if c.key is not None:
        assert f": {c.key}" in first, f"expected key {c.key}; " + where


@pytest.fixture(scope="module")
def corpus_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("corpus")


@pytest.mark.parametrize("c", CASES, ids=IDS)
def test_a_malformed_config_is_refused_without_a_run(c, corpus_dir, capfd, monkeypatch):
    work = corpus_dir / f"{IDS.index(c.id):03d}"
    work.mkdir()
    path = work / "cfg.toml"
    path.write_bytes(c.text.encode("utf-8", "surrogateescape"))
    monkeypatch.chdir(work)
    before = _listing(work)
    code = _core.main(["caviar-core", "validate", str(path)])
    out, err = capfd.readouterr()
    assert code == 2, f"validate: exit {code}\n{out}{err}"
    _check_message(c, path, err, out)
    code = _core.main(["caviar-core", "run", "-q", str(path)])
    out, err = capfd.readouterr()
    assert code == 2, f"run: exit {code}\n{out}{err}"
    _check_message(c, path, err, out)
    assert _listing(work) == before, "run created files"


SUBSET = ["syntax-open-array", "syntax-empty-file", "unknown-param-uav", "type-episode.ts-\"fast\"",
          "nonfinite-modules.uav.params.speed-nan", "range-steps = 0",
          "range-frequency_hz = 0", "path-waypoints-missing", "path-output-name = \"../escaped\"",
          "plugin-plugin = \"no.such.module:X\"", "topic-subscribe-'a..b'", "stage-unknown",
          "range-nats-step_timeout", "unknown-transport-nats"]


@pytest.mark.parametrize("cid", SUBSET)
def test_the_console_script_refuses_them_too(cid, tmp_path):
    c = CASES[IDS.index(cid)]
    path = tmp_path / "cfg.toml"
    path.write_bytes(c.text.encode("utf-8", "surrogateescape"))
    for cmd in ("validate", "run"):
        p = subprocess.run([caviar_core(), cmd, str(path)], cwd=tmp_path, env=caviar_env(), capture_output=True,
                           text=True, timeout=60)
        assert p.returncode == 2, f"{cmd}: exit {p.returncode}\n{p.stdout}{p.stderr}"
        _check_message(c, path, p.stderr, p.stdout)
    assert _listing(tmp_path) == {"cfg.toml"}


# --- precise messages (D8-D11) ----------------------------------------------------------------
def _validate(tmp_path, text, capfd) -> str:
    path = tmp_path / "cfg.toml"
    path.write_text(text)
    assert _core.main(["caviar-core", "validate", str(path)]) == 2
    return capfd.readouterr().err.splitlines()[0]


@pytest.mark.parametrize("old, new, expected", [
    ("speed = 5.0", "speed = nan", "cfg.toml:15: modules.uav.params.speed: expected a finite float, got nan"),
    ("tx_position = [-154.0, 64.0, 120.0]", 'tx_position = ["a", "b", "c"]',
     "cfg.toml:22: modules.comm.params.tx_position: expected list[float], item 0 is str 'a'"),
    ('ue_id = "uav1"', "ue_id = 1979-05-27T07:32:00Z",
     'cfg.toml:16: modules.uav.params.ue_id: a TOML date/time is not a parameter value; write it as a string '
     '("1979-05-27T07:32:00Z")'),
    ("frequency_hz = 40e9", "frequency_hz = 0",
     "cfg.toml:23: modules.comm.params.frequency_hz: expected a positive frequency in Hz, got 0.0"),
    ("speed = 5.0", "speed = -1.0", "cfg.toml:15: modules.uav.params.speed: expected a positive number of m/s"),
    ('ue_id = "uav1"', 'ue_id = "uav1"\nwaypoints = "no-such.csv"',
     "cfg.toml:17: modules.uav.params.waypoints: no such file: "),
    ("steps = 3", "steps = 0", "cfg.toml:3: episode.steps: expected at least 1 step"),
    ("ts = 0.1\nsteps = 3", "ts = 1e-300\nduration = 1.0",
     "cfg.toml:3: episode.duration: duration / ts = 1 / 1e-300 = 1e300 steps: more than the 2^53"),
    ("ts = 0.1", "ts = 1e308", "cfg.toml:2: episode.ts: ts = 1e308 s makes virtual time infinite"),
    ('name = "bad"', 'name = "../escaped"', "cfg.toml:8: output.name: expected a plain name"),
])
def test_messages_say_what_is_wrong(tmp_path, capfd, old, new, expected):
    first = _validate(tmp_path, rep(old, new), capfd)
    assert expected in first, first
    assert "no-such.csv" in first or "waypoints" not in expected


def test_a_tiny_duration_is_one_step(tmp_path, capfd, monkeypatch):
    path = tmp_path / "cfg.toml"
    path.write_text(rep("steps = 3", "duration = 1e-12"))
    monkeypatch.chdir(tmp_path)
    assert _core.main(["caviar-core", "run", "-q", str(path)]) == 0, capfd.readouterr()
    import json
    assert json.loads((tmp_path / "runs" / "bad-001" / "run.json").read_text())["steps_done"] == 1


def test_plugins_check_their_params_at_validate_time(tmp_path, capfd):
    text = ('[episode]\nts = 0.1\nsteps = 2\nstages = ["a"]\n[modules.c]\nstage = "a"\n'
            'plugin = "sample_plugins:Checked"\n[modules.c.params]\nlimit = -3\n')
    first = _validate(tmp_path, text, capfd)
    assert first.endswith("cfg.toml:9: modules.c.params.limit: expected a limit >= 0, got -3"), first


# --- bad --set overrides (issue #28): the same promise for what the command line adds ------------
SET_CASES = [
    ("nokey", "--set 'nokey': expected KEY=VALUE"),
    ("=5", "--set '=5': '' is not a dotted key path"),
    ("a..b=1", "--set 'a..b=1': 'a..b' is not a dotted key path"),
    ("episode.ts.x=1", "--set 'episode.ts.x=1': 'ts' is a value, not a table"),
    ("episode=5", "episode: invalid type: integer `5`, expected struct Episode (from --set episode=5)"),
    ("episode.ts=", "cfg.toml:2: episode.ts: invalid type: string \"\", expected f64 (from --set episode.ts=)"),
    ('episode.ts="fast"', "episode.ts: invalid type: string \"fast\""),
    ("episode.steps=0", "cfg.toml:3: episode.steps: expected at least 1 step"),
    ("episode.seed=-1", "episode.seed: invalid value: integer `-1`, expected u64"),
    ("episode.stages=[unterminated", "episode.stages: invalid type: string \"[unterminated\", expected a sequence"),
    ("episode.pace=0", "episode.pace: expected a positive factor of real time"),
    ('episode.behind="later"', "episode.behind: expected one of"),
    ("modules.nope.params.x=1", "modules.nope.stage: this required key is missing (after --set overrides)"),
    # Not in the file: the line of the table it was added to, and the override.
    ("modules.uav.every=0",
     "cfg.toml:11: modules.uav.every: expected a period of at least 1 step (from --set modules.uav.every=0)"),
    ("modules.uav.params.speed=nan", "cfg.toml:15: modules.uav.params.speed: expected a finite float, got nan"),
    ("modules.uav.params.speed=-1.0", "modules.uav.params.speed: expected a positive number of m/s"),
    ('modules.uav.plugin="no.such:X"', "modules.uav.plugin: cannot import 'no.such' for plugin 'no.such:X'"),
    ('modules.comm.params.tx_position=["a"]', "modules.comm.params.tx_position: expected list[float]"),
    ('output.name="../x"', "output.name: expected a plain name"),
    ('transport.kind="pigeon"', "transport.kind"),
]


@pytest.mark.parametrize("override, expected", SET_CASES, ids=[o for o, _ in SET_CASES])
def test_a_bad_set_override_is_refused_without_a_run(override, expected, tmp_path, capfd, monkeypatch):
    path = tmp_path / "cfg.toml"
    path.write_text(BASE)
    monkeypatch.chdir(tmp_path)
    for cmd in ("validate", "run"):
        code = _core.main(["caviar-core", cmd, str(path), "--set", override])
        out, err = capfd.readouterr()
        assert code == 2, f"{cmd}: exit {code}\n{out}{err}"
        assert "Traceback" not in err + out and err.startswith("error: "), err
        first = err.splitlines()[0]
        assert str(path) in first and expected in first, first
    assert _listing(tmp_path) == {"cfg.toml"}, "run created files"


@pytest.mark.parametrize("extra", [[], ["--strict"], ["--set", "episode.step_timeout=30"],
                                   ["--set", "output.checkpoint_every=5", "--strict"]])
def test_with_overrides_messages_name_the_files_own_line(extra, tmp_path, capfd):
    """--strict and --set add keys to tables above the bad one, which shifts the lines of the
    overridden text; messages still name the line in the file (and the override, when the bad
    value came from one)."""
    path = tmp_path / "cfg.toml"
    path.write_text(BASE.replace('ue_id = "uav1"', 'ue_id = "uav1"\nspeed_x = 1'))
    line = BASE.splitlines().index('ue_id = "uav1"') + 2
    assert _core.main(["caviar-core", "validate", str(path), *extra]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert first.startswith(f"error: {path}:{line}: modules.uav.params"), first
    path.write_text(BASE)
    every = BASE.splitlines().index('plugin = "waypoint-flight"') + 1
    path.write_text(BASE.replace('plugin = "waypoint-flight"', 'plugin = "waypoint-flight"\nevery = 1'))
    assert _core.main(["caviar-core", "validate", str(path), *extra, "--set", "modules.uav.every=0"]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert first == (f"error: {path}:{every + 1}: modules.uav.every: expected a period of at least 1 step "
                     "(from --set modules.uav.every=0)"), first
