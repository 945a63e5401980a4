"""A standard hexagonal layout in a ray-traced scene, and ray-traced against TR 38.901 on it
(issue #44, part 4): where a point is outdoors, the drop in a city, the free-space
limit checked against Friis, the bad input, and the side-by-side command."""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest

from caviar import _core
from caviar_plugins.network.layout import LayoutSettings, site_positions
from caviar_plugins.rt.scene import load_scene, open_sky
from caviar_plugins.tools import calibration
from configs import episode, output
from network_configs import MAPS, REPORTS, radio_network, ray_traced, ue_reports

ROOT = pathlib.Path(__file__).resolve().parents[1]
OSM_CITY = ROOT / "blueprints" / "osm-city" / "scene" / "scene.xml"
C = 299_792_458.0

LAYOUT = {"kind": "hex", "rings": 1, "isd_m": 200.0, "height_m": 10.0, "min_distance_m": 10.0, "wraparound": False,
          "indoor_share": 0.0, "ues_per_sector": 2, "redrop": "every-step", "center_m": [0.0, 0.0]}
NETWORK = (episode(0.001, ["communications"], steps=2, seed=3) + output(name="rt-layout", analysis=[*REPORTS, *MAPS])
           + radio_network(subscribe=[], carrier_hz=6e9, tx_power_dbm=44.0, array=[1, 1], link_model="shannon",
                           report_cells=1, layout=LAYOUT, column={"elements": 10},
                           **ray_traced("empty", max_depth=1, samples_per_src=10000, mode="hold")))


def _run(tmp_path, text: str, name: str = "a") -> list[dict]:
    import caviar

    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(text)
    with caviar.Simulation.from_toml(cfg, out=tmp_path / name) as sim:
        return ue_reports(sim.run(progress=False))


def test_open_sky_is_false_inside_a_building_and_true_in_the_street_and_on_the_roof():
    import sionna.rt.scene as shipped

    scene = load_scene(shipped.simple_street_canyon)
    box = scene.objects["building_2"].mi_mesh.bbox()
    lo, hi = np.array(box.min), np.array(box.max)
    middle = (lo + hi) / 2
    points = np.array([[middle[0], middle[1], 1.5],  # inside the building
                       [middle[0], 0.0, 1.5],  # the street between building_6 (y < -8.6) and it (y > 10.3)
                       [middle[0], middle[1], hi[2] + 1.0]])  # above its roof
    assert open_sky(scene, points).tolist() == [False, True, True]
    assert open_sky(scene, np.zeros((0, 3))).shape == (0,)


def test_a_layout_ray_traced_in_free_space_gives_friis_through_the_sector_pattern(tmp_path):
    """No scene: the one traced path is the direct one, so every UE's coupling loss equals
    the free-space channel's (Friis through the same sector pattern and column) on the same
    drop, and its serving cell's loss equals Friis at the UE's 3D distance less the gain."""
    traced = _run(tmp_path, NETWORK, "traced")
    free = _run(tmp_path, NETWORK.replace('channel = "ray-traced"', 'channel = "free-space"'), "free")
    assert len(traced) == len(free) == 2 * 21 * 2
    assert [u["position_m"] for u in traced] == [u["position_m"] for u in free]  # (the same drops)
    assert [u["serving_cell"] for u in traced] == [u["serving_cell"] for u in free]
    np.testing.assert_allclose([u["coupling_loss_db"] for u in traced], [u["coupling_loss_db"] for u in free],
                               atol=0.02)
    # Friis at 3D distance, without any pattern: the loss is at least Friis less the panel's
    # peak (8 dBi element + 10 dB column), and a UE can not be served by a cell behind it.
    sites = site_positions(LayoutSettings(rings=1, isd_m=200.0, height_m=10.0))
    for u in traced:
        site = sites[int(u["serving_cell"].split("/")[0][1:])]
        d = math.dist([*site, 10.0], u["position_m"])
        friis = 20 * math.log10(4 * math.pi * d * 6e9 / C)
        assert friis - 18.0 - 0.05 <= u["coupling_loss_db"] <= friis + 30.0


def test_a_drop_in_a_city_puts_every_ue_outdoors_in_its_own_sector(tmp_path):
    text = NETWORK.replace('scene = "empty"', f'scene = "{OSM_CITY.as_posix()}"').replace(
        "center_m = [0.0, 0.0]", "center_m = [10.0, 0.0]")
    ues = _run(tmp_path, text.replace("steps = 2", "steps = 1"))
    scene = load_scene(str(OSM_CITY))
    layout = LayoutSettings(rings=1, isd_m=200.0, height_m=10.0, min_distance_m=10.0, wraparound=False,
                            indoor_share=0.0, ues_per_sector=2, center_m=(10.0, 0.0))
    positions = np.array([u["position_m"] for u in ues])
    assert open_sky(scene, positions).all()
    sites = site_positions(layout)
    sector = np.arange(len(ues)) // 2  # drop<k>: sector k // 2, site sector // 3
    home = sector // 3
    d = np.linalg.norm(positions[:, :2] - sites[home], axis=1)
    # In its sector's cell: the hexagon of radius ISD/3 centred ISD/3 along the boresight (30°, 150°, 270°).
    bore = np.radians(30.0 + 120.0 * (sector % 3))
    centre = sites[home] + 200.0 / 3 * np.stack([np.cos(bore), np.sin(bore)], -1)
    assert (d >= 10.0 - 1e-6).all() and (np.linalg.norm(positions[:, :2] - centre, axis=1) <= 200.0 / 3 + 1e-6).all()
    # The same drop in free space (nothing to move): the UEs it put under a roof, and only they, moved.
    first = np.array([u["position_m"] for u in _run(tmp_path, NETWORK.replace("steps = 2", "steps = 1").replace(
        "center_m = [0.0, 0.0]", "center_m = [10.0, 0.0]"), "free")])
    moved = np.any(np.abs(first - positions) > 0.01, axis=1)
    assert moved.any()
    np.testing.assert_array_equal(moved, ~open_sky(scene, first))


@pytest.mark.parametrize("edit, replacement, key, says", [
    ("wraparound = false", "wraparound = true", "layout.wraparound", "a ray-traced scene is finite"),
    ("indoor_share = 0.0", "indoor_share = 0.8", "layout.indoor_share", "outdoor UEs only"),
    ("center_m = [0.0, 0.0]", "center_m = [0.0]", "layout.center_m", "expected tuple[float, float] (2 items)"),
])
def test_bad_raytraced_layout_input_names_the_key(tmp_path, capfd, edit, replacement, key, says):
    cfg = tmp_path / "net.toml"
    cfg.write_text(NETWORK.replace(edit, replacement, 1))
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert f"modules.net.params.{key}:" in first and says in first, first


def test_a_site_under_a_roof_stops_the_run_before_its_first_step_naming_the_centre(tmp_path):
    import caviar

    scene = load_scene(str(OSM_CITY))
    sites = site_positions(LayoutSettings(rings=1, isd_m=200.0, height_m=10.0))
    grid = np.stack(np.meshgrid(np.arange(-100, 101, 10.0), np.arange(-300, 301, 10.0)), -1).reshape(-1, 2)
    # A centre that puts the centre site, and it alone, under a roof.
    spots = (grid[:, None, :] + sites[None]).reshape(-1, 2)
    inside = ~open_sky(scene, np.c_[spots, np.full(len(spots), 10.0)]).reshape(len(grid), len(sites))
    x, y = grid[int(np.argmax(inside[:, 0] & ~inside[:, 1:].any(axis=1)))]
    assert inside[int(np.argmax(inside[:, 0] & ~inside[:, 1:].any(axis=1))), 0]
    text = NETWORK.replace('scene = "empty"', f'scene = "{OSM_CITY.as_posix()}"').replace(
        "center_m = [0.0, 0.0]", f"center_m = [{x}, {y}]")
    cfg = tmp_path / "net.toml"
    cfg.write_text(text)
    with pytest.raises(caviar.RunError) as err:
        with caviar.Simulation.from_toml(cfg, out=tmp_path / "runs") as sim:
            sim.run(progress=False)
    assert "module 'net' failed in setup: params.layout.center_m:" in str(err.value)
    assert "site(s) S0 under a roof" in str(err.value)


def test_side_by_side_writes_both_channels_cdfs_and_their_difference(tmp_path, capsys):
    assert calibration.main(["ray-traced", "--scene", str(OSM_CITY), "--drops", "1", "--samples", "20000",
                             "--max-depth", "1", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "raytraced-vs-38.901-umi.json").read_text())
    assert (tmp_path / "raytraced-vs-38.901-umi.png").stat().st_size > 10_000
    assert (tmp_path / "raytraced-vs-38.901-umi-map.png").stat().st_size > 10_000
    # The centre the command found has every site in the open.
    center = result["settings"]["layout"]["center_m"]
    sites = site_positions(LayoutSettings(rings=1, isd_m=200.0, height_m=10.0, center_m=tuple(center)))
    assert open_sky(load_scene(str(OSM_CITY)), np.c_[sites, np.full(7, 10.0)]).all()
    traced, stochastic = result["channels"]["ray-traced"], result["channels"]["38.901-umi"]
    assert traced["samples"] + traced["uncovered"] == stochastic["samples"] == 21 * 10
    assert stochastic["uncovered"] == 0
    for metric in calibration.METRICS:
        assert len(traced[metric]) == 101 and np.all(np.diff(traced[metric]) >= 0)
        for p in (5, 50, 95):
            assert result["difference_db"][metric][f"p{p}"] == pytest.approx(
                traced[metric][p] - stochastic[metric][p], abs=0.011)
    # Every ray-traced loss is at least free space less the panel's peak at the closest a UE can be.
    closest = math.hypot(10.0, 10.0 - 1.5)
    assert traced["coupling_loss_db"][0] >= 20 * math.log10(4 * math.pi * closest * 6e9 / C) - 18.0
    assert "ray-traced − 38.901 coupling_loss_db" in capsys.readouterr().out


@pytest.mark.parametrize("argv, says", [
    (["--center", "ten"], "--center: expected X,Y"),
    (["--scene", "no/such/scene.xml"], "--scene: no/such/scene.xml does not exist (expected a Mitsuba scene file"),
    (["--drops", "0"], "--drops: expected a whole number from 1 to 10000, got 0"),
])
def test_side_by_side_refuses_bad_arguments(argv, says, capsys, tmp_path):
    assert calibration.main(["ray-traced", *argv, "--out", str(tmp_path)]) == 2
    assert says in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
