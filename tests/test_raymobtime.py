"""The multimodal dataset (issue #43, part 3): beam-dataset records with the UAV's LiDAR sweep
and camera image, and ``caviar-core export raymobtime`` writing them in Raymobtime's files;
the occupancy grid against cells computed by hand."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from caviar_plugins.tools.export.raymobtime import BASE_STATION, OBSTACLE, UE, occupancy_grid
from configs import episode, module, output, sionna_link
from conftest import ROOT


def test_the_occupancy_grid_puts_each_point_in_the_cell_computed_by_hand():
    centre = np.array([10.0, -5.0, 30.0])
    # A 40 × 40 × 20 grid of 1 m cells: x from -10 to 30, y from -25 to 15, z from 14 to 34.
    points = np.array([[11.5, -5.5, 26.8, 0.3], [10.2, -4.9, 14.0, 0.3], [60.0, 0.0, 20.0, 0.3]])
    grid = occupancy_grid(points, centre, (40, 40, 20), 1.0, base_station=np.array([10.0, -5.0, 120.0]))
    assert grid.shape == (40, 40, 20) and grid.dtype == np.int8
    assert grid[21, 19, 12] == OBSTACLE  # (11.5 + 10, -5.5 + 25, 26.8 - 14)
    assert grid[20, 20, 0] == OBSTACLE  # on the grid's floor
    assert (grid == OBSTACLE).sum() == 2  # the third point is 50 m away: outside
    assert grid[20, 20, 16] == UE  # the UE's own cell, 0.8 of the height above the floor
    assert grid[20, 20, 19] == BASE_STATION  # straight up: the top cell of its column
    # A base station far to the east and level: the last cell of the UE's row.
    east = occupancy_grid(np.zeros((0, 3)), centre, (40, 40, 20), 1.0, base_station=np.array([500.0, -5.0, 30.0]))
    assert east[39, 20, 16] == BASE_STATION and (east != 0).sum() == 2


DATASET = (episode(0.5, ["mobility", "sensing", "communications", "dataset"], steps=3, seed=7)
           + output(analysis=["communications.throughput", "communications.channel.*", "communications.state",
                              "communications.prediction", "communications.paths.*", "dataset.record",
                              "3D.lidar.*.sweep", "3D.lidar.*.file", "3D.camera.*.file", "3D.camera.*.depth"],
                    exclude=["communications.channel.>", "3D.lidar.*", "3D.camera.*"])
           + module("uav", "mobility", "random-waypoint-flight", {"spread": 15.0, "altitude": [8.0, 12.0],
                                                                   "speed": 5.0})
           + module("lidar", "sensing", "lidar", {"scene": "central_park", "raytracing": {"threads": 1},
                                                   "sensor": {"channels": 16, "horizontal_resolution_deg": 1.0}})
           + module("camera", "sensing", "camera")
           + sionna_link(tx_position=[-154.0, 64.0, 120.0])
           + module("dataset", "dataset", "beam-dataset"))


def test_export_raymobtime_writes_every_modality_of_every_record(tmp_path, cli):
    (tmp_path / "dataset.toml").write_text(DATASET)
    cli("run", "dataset.toml", "--out", "run", "-q", check=0)
    from caviar_plugins.beam_selection.dataset import load_multimodal

    arrays, sweeps, images, ues = load_multimodal(tmp_path / "run")
    assert len(ues) == 3 and all(s is not None and s.shape[1] == 6 for s in sweeps)
    assert all(im is not None and im.shape == (120, 160, 3) for im in images)
    p = cli("export", "raymobtime", "run", "out", "--grid", "30,30,10", check=0)
    assert "3 records (3 with LiDAR, 3 with an image)" in p.stdout
    out = tmp_path / "out"
    with open(out / "CoordVehiclesRxPerScene.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["SceneID"] for r in rows] == ["0", "1", "2"] and {r["Val"] for r in rows} == {"V"}
    np.testing.assert_allclose([[float(r[k]) for k in "xyz"] for r in rows], arrays["position"], atol=1e-3)
    beams = np.load(out / "beams_output.npz")["output_classification"]
    np.testing.assert_array_equal(beams, arrays["gains"].astype(np.float32))
    lidar = np.load(out / "lidar_input.npz")["input_classification"]
    assert lidar.shape == (3, 30, 30, 10) and lidar.dtype == np.int8
    for k in range(3):
        expected = occupancy_grid(sweeps[k], arrays["position"][k], (30, 30, 10), 1.0, np.array([-154.0, 64.0, 120.0]))
        np.testing.assert_array_equal(lidar[k], expected)
        assert (lidar[k] == OBSTACLE).sum() > 50  # the ground and trees under the UAV
    np.testing.assert_array_equal(np.load(out / "img_input.npz")["inputs"], np.stack(images))
    meta = json.loads((out / "meta.json").read_text())
    assert meta["transmitter"] == [-154.0, 64.0, 120.0] and meta["differs_from_raymobtime"]


@pytest.mark.parametrize("args, says", [
    (["raymobtime", "nothing", "out"], "RUN_DIR: nothing does not exist"),
    (["raymobtime", "run", "out", "--grid", "a,b"], "--grid: expected X,Y,Z cells (numbers)"),
    (["raymobtime", "run", "out", "--grid", "0,10,10"], "--grid: expected X,Y,Z: whole numbers of cells, at least 1"),
])
def test_export_raymobtime_refuses_bad_input(tmp_path, cli, args, says):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text("{}")
    p = cli("export", *args, check=2)
    assert says in p.stderr, p.stderr
    assert not (tmp_path / "out").exists()


def test_a_run_without_dataset_records_is_refused(tmp_path, cli):
    cli("run", ROOT / "blueprints" / "quickstart" / "config.toml", "--out", "run", "-q", "--set", "episode.steps=2",
        check=0)
    p = cli("export", "raymobtime", "run", "out", check=2)
    assert "no dataset records" in p.stderr and "beam-dataset" in p.stderr
