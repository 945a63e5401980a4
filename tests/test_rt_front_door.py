"""One way into the ray tracer (issue #57): every module that traces takes its settings as
``raytracing = { … }`` (:class:`caviar_plugins.rt.settings.TraceSettings`), gets its scene
from :func:`caviar_plugins.rt.scene.build_scene`, and only ``caviar_plugins.rt`` imports
Sionna RT."""

from __future__ import annotations

import ast
import dataclasses
import pathlib

import numpy as np
import pytest

import caviar
from caviar_plugins.rt.settings import TraceSettings, with_raytracing

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = [ROOT / "plugins" / "caviar_plugins", ROOT / "python" / "caviar"]
RT = ROOT / "plugins" / "caviar_plugins" / "rt"


def _imports_sionna_rt(tree: ast.AST) -> list[int]:
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name == "sionna.rt" or a.name.startswith("sionna.rt.")
                                                for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.module is not None and (
                node.module == "sionna.rt" or node.module.startswith("sionna.rt.")
                or (node.module == "sionna" and any(a.name == "rt" for a in node.names))):
            lines.append(node.lineno)
    return lines


def test_only_the_rt_package_imports_sionna_rt():
    """``import sionna.rt`` (in any spelling) appears in ``caviar_plugins/rt/`` only: the SAR
    link, the network, its radio map, the LiDAR and the exports reach the ray tracer through it."""
    found = []
    for package in PACKAGES:
        for path in package.rglob("*.py"):
            if RT in path.parents:
                continue
            found += [f"{path.relative_to(ROOT)}:{line}" for line in _imports_sionna_rt(ast.parse(path.read_text()))]
    assert not found, f"import sionna.rt outside caviar_plugins/rt: {found}"


def _sionna_entries(tree: ast.AST) -> list[tuple[int, str]]:
    """Calls that enter Sionna RT without the front door: its solvers, its scene loader
    (``rt.load_scene``), or an intersection with a Sionna scene's Mitsuba scene."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        owner = f.value if isinstance(f, ast.Attribute) else None
        owner_name = owner.attr if isinstance(owner, ast.Attribute) else owner.id if isinstance(owner, ast.Name) else ""
        if (name in ("PathSolver", "RadioMapSolver") or (name == "load_scene" and owner_name in ("rt", "sionna"))
                or (name.startswith("ray_intersect") and owner_name == "mi_scene")):
            found.append((node.lineno, name))
    return found


def test_every_tracing_module_builds_its_scene_through_the_front_door():
    """No module outside ``rt`` loads a Sionna scene, makes a solver or intersects rays with
    a Sionna scene itself. (The camera renders with Mitsuba, a scene of its own: not Sionna RT.)"""
    found = []
    for package in PACKAGES:
        for path in package.rglob("*.py"):
            if RT not in path.parents:
                found += [f"{path.relative_to(ROOT)}:{line} {name}"
                          for line, name in _sionna_entries(ast.parse(path.read_text()))]
    assert not found, found
    assert _sionna_entries(ast.parse("import sionna.rt as rt\nrt.load_scene()\nrt.PathSolver()\n"
                                     "s.mi_scene.ray_intersect(r)\n")) == [(2, "load_scene"), (3, "PathSolver"),
                                                                           (4, "ray_intersect")]


HEAD = '[episode]\nts = 0.5\nsteps = 1\nstages = ["c"]\n[modules.m]\nstage = "c"\n'


@pytest.mark.parametrize("plugin, params, key, new", [
    ("sionna-link", "samples_per_src = 1000", "samples_per_src", "raytracing.samples_per_src"),
    ("sionna-link", "threads = 1", "threads", "raytracing.threads"),
    ("sionna-link", "shoot_cache = false", "shoot_cache", "raytracing.shoot_cache"),
    ("sionna-link", "los = false", "los", "raytracing.los"),
    ("sionna-traffic-link", "max_depth = 2", "max_depth", "raytracing.max_depth"),
    ("lidar", "threads = 1", "threads", "raytracing.threads"),
    ("radio-network", 'raytracing = { scene = "empty" }', "raytracing.scene", "scene"),
    ("radio-network", "raytracing = { refresh_s = 0.5 }", "raytracing.refresh_s", "evolution.refresh_s"),
    ("radio-network", 'raytracing = { evolve = "hold" }', "raytracing.evolve", "evolution.mode"),
    ("radio-network", "radio_map = { samples_per_tx = 1000 }", "radio_map.samples_per_tx",
     "radio_map.raytracing.samples_per_src"),
])
def test_an_old_flat_key_is_refused_with_the_new_key_named(tmp_path, plugin, params, key, new):
    cfg = tmp_path / "exp.toml"
    cfg.write_text(HEAD + f'plugin = "{plugin}"\n[modules.m.params]\n{params}\n')
    with pytest.raises(caviar.ConfigError) as e:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    text = str(e.value)
    assert f"modules.m.params.{key}:" in text and f"has moved: write it as {new}" in text, text
    assert "exp.toml:" in text, text


def test_a_partial_table_keeps_the_modules_own_defaults(tmp_path):
    """``raytracing = { threads = 1 }`` changes the threads only: the network keeps its 1e5
    rays to depth 3 without diffuse reflection, the SAR link its 1e6 to depth 5 with it."""
    from caviar._host import check_params
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.network.raytraced import NETWORK_RAYS
    from caviar_plugins.radio.sionna_link import SionnaLink

    sites = [{"name": "A", "position": [0.0, 0.0, 25.0], "azimuths_deg": [0.0]}]
    net = check_params(RadioNetwork, {"sites": sites, "link_model": "shannon", "raytracing": {"threads": 1}})
    assert net.raytracing == dataclasses.replace(NETWORK_RAYS, threads=1)
    assert net.raytracing.samples_per_src == 100_000 and not net.raytracing.diffuse_reflection
    link = check_params(SionnaLink, {"raytracing": {"threads": 1, "max_depth": 2}})
    assert link.raytracing == TraceSettings(threads=1, max_depth=2)
    assert link.raytracing.samples_per_src == 1_000_000 and link.raytracing.diffuse_reflection


@pytest.mark.parametrize("table, key", [
    ({"samples_per_src": 0}, "samples_per_src"),
    ({"max_depth": -1}, "max_depth"),
    ({"threads": -2}, "threads"),
    ({"shoot_cache": "sometimes"}, "shoot_cache"),
    ({"seed": 1.5}, "seed"),
    ({"samples_per_sorc": 10}, "samples_per_sorc"),
])
def test_bad_ray_settings_name_their_key(table, key):
    from caviar._host import check_params
    from caviar_plugins.radio.sionna_link import SionnaLink

    with pytest.raises(caviar.ConfigError) as e:
        check_params(SionnaLink, {"raytracing": table})
    assert e.value.key == f"params.raytracing.{key}", (e.value.key, str(e.value))


def test_a_lidar_refuses_ray_settings_it_cannot_use():
    from caviar._host import check_params
    from caviar_plugins.lidar.plugin import Lidar

    assert check_params(Lidar, {"raytracing": {"threads": 1}}).raytracing.threads == 1
    with pytest.raises(caviar.ConfigError, match=r"a LiDAR casts one ray per beam") as e:
        check_params(Lidar, {"raytracing": {"samples_per_src": 1000}})
    assert e.value.key == "params.raytracing.samples_per_src"


def test_the_settings_reach_sionna_as_written():
    """What the TOML's table holds is what Sionna's ``PathSolver`` is called with: the
    front door passes ``raytracing`` on, field for field (the solver's seed: the run's, or
    ``raytracing.seed``)."""
    from caviar_plugins.radio import RadioConfig, RadioScene

    rays = TraceSettings(samples_per_src=1234, max_depth=1, diffuse_reflection=False, refraction=False, threads=1,
                         shoot_cache=False, max_num_paths_per_src=4321)
    radio = RadioScene(RadioConfig(scene="empty", uav_mesh=False, raytracing=rays), seed=7)
    seen = {}
    solver = radio.tracer.solver

    def recording(scene, **options):
        seen.update(options)
        return solver(scene, **options)

    radio.tracer.solver = recording
    radio.place({"uav1": np.array([10.0, 0.0, 30.0])})
    link = radio.solve()["uav1"]
    assert seen == {"max_depth": 1, "samples_per_src": 1234, "los": True, "specular_reflection": True,
                    "diffuse_reflection": False, "refraction": False, "diffraction": True, "seed": 7,
                    "synthetic_array": True, "max_num_paths_per_src": 4321}
    assert link.n_paths == 1  # (free space: the line of sight)
    pinned = RadioScene(RadioConfig(scene="empty", uav_mesh=False, raytracing=dataclasses.replace(rays, seed=3)),
                        seed=7)
    assert pinned.tracer.options["seed"] == 3


def test_with_raytracing_takes_flat_keys_into_the_table():
    from caviar_plugins.network.radio_map import MAP_RAYS, RadioMapSettings
    from caviar_plugins.radio import RadioConfig

    cfg = with_raytracing(RadioConfig, scene="empty", samples_per_src=10, threads=1)
    assert cfg.scene == "empty" and cfg.raytracing == TraceSettings(samples_per_src=10, threads=1)
    m = with_raytracing(RadioMapSettings, cell_size_m=5.0, max_depth=0)
    assert m.raytracing == dataclasses.replace(MAP_RAYS, max_depth=0)
