"""Bad invocations of the tools' commands (``caviar-core calibrate``, ``export``, ``scene``;
issue #55): each ends before any work starts with exit status 2 and one line on stderr that
names the flag, without a traceback. In-process through each command's ``main`` (fast), and
two through the ``caviar-core`` executable."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import pytest

from caviar_plugins.tools.calibration.cli import main as calibrate
from caviar_plugins.tools.export.cli import main as export
from caviar_plugins.tools.scene.cli import main as scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENE = ROOT / "plugins" / "caviar_plugins" / "scenes"


@pytest.fixture
def place(tmp_path):
    """A file, a folder, a non-JSON file, a JSON file that is not the companies' CDFs, a run
    directory (with run.json) and an OSM-named file."""
    (tmp_path / "a-file.txt").write_text("x")
    (tmp_path / "a-folder").mkdir()
    (tmp_path / "not.json").write_text("not json {")
    (tmp_path / "other.json").write_text(json.dumps({"hello": 1}))
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text("{}")
    (tmp_path / "map.osm").write_text("<osm></osm>")
    return tmp_path


def _scene_file() -> str:
    return str(next(SCENE.glob("*/*.xml")))


# (command, arguments ({t}: the fixture's folder), the flag the line must name)
CASES = [
    (calibrate, "38.901 --out {t}/a-file.txt", "--out"),
    (calibrate, "38.901 --out {t}/a-file.txt/below", "--out"),
    (calibrate, "38.901 --out /proc/caviar-cannot-write-here", "--out"),
    (calibrate, "38.901 --reference {t}/a-folder --out {t}/o", "--reference"),
    (calibrate, "38.901 --reference {t}/not.json --out {t}/o", "--reference"),
    (calibrate, "38.901 --reference {t}/other.json --out {t}/o", "--reference"),
    (calibrate, "38.901 --reference {t}/missing.json --out {t}/o", "--reference"),
    (calibrate, "38.901 --seed -1 --out {t}/o", "--seed"),
    (calibrate, "38.901 --seed 99999999999999999999 --out {t}/o", "--seed"),
    (calibrate, "38.901 --drops 0 --out {t}/o", "--drops"),
    (calibrate, "38.901 --drops many --out {t}/o", "--drops"),
    (calibrate, "38.901 --carrier nan --out {t}/o", "--carrier"),
    (calibrate, "38.901 --scenario InH --out {t}/o", "--scenario"),
    (calibrate, "38.901 --spec-version 18.0 --out {t}/o", "--spec-version"),
    (calibrate, "ray-traced --scene {scene} --center nan,nan --out {t}/o", "--center"),
    (calibrate, "ray-traced --scene {scene} --center 1,2,3 --out {t}/o", "--center"),
    (calibrate, "ray-traced --scene {scene} --samples -1 --out {t}/o", "--samples"),
    (calibrate, "ray-traced --scene {scene} --max-depth -1 --out {t}/o", "--max-depth"),
    (calibrate, "ray-traced --scene {t}/missing.xml --out {t}/o", "--scene"),
    (export, "deepmimo {t}/missing {t}/o", "RUN_DIR"),
    (export, "deepmimo {t}/a-folder {t}/o", "RUN_DIR"),
    (export, "deepmimo {t}/run {t}/a-file.txt", "OUT"),
    (export, "deepmimo {t}/run {t}/a-file.txt/o", "OUT"),
    (export, "deepmimo {t}/run {t}/o --module ' '", "--module"),
    (export, "raymobtime {t}/run {t}/o --grid 0,40,20", "--grid"),
    (export, "raymobtime {t}/run {t}/o --grid 40,40", "--grid"),
    (export, "raymobtime {t}/run {t}/o --cell nan", "--cell"),
    (export, "raymobtime {t}/run {t}/o --cell -1", "--cell"),
    (export, "raymobtime {t}/run {t}/o --tx nan,0,10", "--tx"),
    (scene, "build {t}/missing.osm --out {t}/o", "INPUT"),
    (scene, "build {t}/map.osm --out {t}/a-file.txt", "--out"),
    (scene, "build {t}/map.osm --out {t}/o --center nan,24 --radius 100", "--center"),
    (scene, "build {t}/map.osm --out {t}/o --center 95,24 --radius 100", "--center"),
    (scene, "build {t}/map.osm --out {t}/o --center 60,24 --radius -5", "--radius"),
    (scene, "build {t}/map.osm --out {t}/o --decimate nan", "--decimate"),
    (scene, "build {t}/map.osm --out {t}/o --default-height inf", "--default-height"),
]


@pytest.mark.parametrize("command, args, flag", CASES, ids=[f"{c.__module__.split('.')[-2]}:{a}" for c, a, _ in CASES])
def test_a_bad_flag_is_one_line_naming_it_before_any_work(command, args, flag, place, capsys):
    import shlex

    argv = shlex.split(args.format(t=place, scene=_scene_file()))
    assert command(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert flag in lines[0] and "error" in lines[0], lines[0]
    assert "Traceback" not in captured.err + captured.out
    assert not (place / "o").exists()  # nothing was made


def test_the_executable_says_the_same_in_one_line(place):
    exe = pathlib.Path(sys.executable).parent / "caviar-core"
    for argv, flag in ((["calibrate", "38.901", "--seed", "-1", "--out", str(place / "o")], "--seed"),
                       (["export", "raymobtime", str(place / "run"), str(place / "o"), "--cell", "nan"], "--cell")):
        r = subprocess.run([str(exe), *argv], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and flag in r.stderr and "Traceback" not in r.stderr
