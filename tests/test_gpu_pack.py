"""What ``scripts/gpu-pack.sh`` sends to the lent GPU machine (issue #53, part 1), checked here:
Sionna RT imports with the notebook stand-ins in place of the real packages (the stand-in
``pythreejs`` once raised where ``rt/viewer.py`` names ``p3s.PerspectiveCamera`` in an
annotation, and every Sionna blueprint stopped at step 0 there), and the pack holds what
live-uav needs."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import ROOT

STANDINS = ROOT / "scripts" / "gpu-standins"
NOTEBOOK = ("ipywidgets", "pythreejs", "IPython")

IMPORT = f"""
import importlib.abc, sys
standins = {str(STANDINS)!r}
sys.path.insert(0, standins)


class OnlyStandIns(importlib.abc.MetaPathFinder):
    '''The real notebook packages hidden: a module of theirs is found in the stand-ins or not at all.'''

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {NOTEBOOK!r}:
            from importlib.machinery import PathFinder

            spec = PathFinder.find_spec(name, path if path is not None else [standins])
            if spec is None or not (spec.origin or "").startswith(standins):
                raise ImportError(f"{{name}}: hidden (only the stand-ins are on this machine)")
            return spec
        return None


sys.meta_path.insert(0, OnlyStandIns())
import sionna.rt
import pythreejs, ipywidgets, IPython
assert all(m.__file__.startswith(standins) for m in (pythreejs, ipywidgets, IPython))
assert sionna.rt.viewer is not None
try:
    pythreejs.PerspectiveCamera()
except RuntimeError as e:
    print("refused:", e)
scene = sionna.rt.load_scene(sionna.rt.scene.simple_street_canyon)
print("scene objects:", len(scene.objects))
"""


def run(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env,
                          cwd=ROOT)


def test_sionna_rt_imports_with_the_standins_and_the_notebook_packages_hidden():
    p = run(IMPORT)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "refused: pythreejs.PerspectiveCamera: a stand-in" in p.stdout
    assert "scene objects:" in p.stdout and not p.stdout.strip().endswith("scene objects: 0")


def test_the_old_standin_fails_as_it_did_on_the_h200(tmp_path):
    """The check sees the H200's failure: a ``pythreejs`` whose ``__getattr__`` raises."""
    old = tmp_path / "standins"
    for name in NOTEBOOK:
        (old / name).parent.mkdir(parents=True, exist_ok=True)
    import shutil

    shutil.copytree(STANDINS, old, dirs_exist_ok=True)
    (old / "pythreejs" / "__init__.py").write_text(
        "def __getattr__(name):\n    raise ImportError(f'pythreejs.{name}: a stand-in')\n")
    p = run(IMPORT.replace(repr(str(STANDINS)), repr(str(old))))
    assert p.returncode != 0 and "pythreejs.PerspectiveCamera: a stand-in" in p.stderr, p.stderr[-2000:]


def test_the_packs_trimmed_pymavlink_parses_what_live_uav_sends(tmp_path):
    """gpu-pack.sh keeps pymavlink's ``all`` dialect alone (48 MB -> a few): its own trimming
    lines, run on a copy of this machine's pymavlink, leave a package that packs and parses a
    MAVLink 2 message."""
    import shutil

    import pymavlink

    text = (ROOT / "scripts" / "gpu-pack.sh").read_text()
    assert '"pymavlink==$(version pymavlink)"' in text
    trimming = text[text.index("# pymavlink (live-uav)"):text.index("find \"$site\" -name '__pycache__'")]
    site = tmp_path / "site"
    shutil.copytree(os.path.dirname(pymavlink.__file__), site / "pymavlink")
    subprocess.run(["bash", "-c", f"set -e; site={site}\n{trimming}"], check=True)
    assert not (site / "pymavlink/dialects/v10").exists()
    assert sorted(p.name for p in (site / "pymavlink/dialects/v20").glob("*.py")) == ["__init__.py", "all.py"]
    code = ("import sys\n"
            f"sys.path.insert(0, {str(site)!r})\n"
            "from pymavlink.dialects.v20 import all as mavlink\n"
            "assert mavlink.__file__.startswith(sys.path[0])\n"
            "m = mavlink.MAVLink(None, srcSystem=1)\n"
            "msg = m.global_position_int_encode(1000, 473977420, 85455940, 50000, 20000, 100, -50, 0, 9000)\n"
            "got = m.parse_char(msg.pack(m))\n"
            "print(got.get_type(), got.lat, got.relative_alt)\n")
    p = run(code)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["GLOBAL_POSITION_INT", "473977420", "20000"]
