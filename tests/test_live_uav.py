"""The live-uav blueprint as a user runs it: its scripted MAVLink vehicle in one process,
`caviar-core run` in another, on the wall clock; the run follows the vehicle and
predicts its link (a few steps, with fewer rays)."""

from __future__ import annotations

import json
import pathlib
import socket
import subprocess
import sys

import numpy as np
import pytest

import caviar
from caviar_plugins import DATA
from caviar_plugins.mobility import read_waypoints

pytest.importorskip("pymavlink")

ROOT = pathlib.Path(__file__).resolve().parent.parent
BLUEPRINT = ROOT / "blueprints" / "live-uav"


def _distance_to_polyline(q: np.ndarray, pts: np.ndarray) -> float:
    a, b = pts[:-1], pts[1:]
    ab = b - a
    f = np.clip(((q - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + f[:, None] * ab - q, axis=1).min())


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_live_uav_blueprint_follows_its_vehicle_and_predicts(cli, tmp_path):
    port = _free_udp_port()
    sender = subprocess.Popen([sys.executable, str(BLUEPRINT / "send_mavlink.py"), "--to", f"127.0.0.1:{port}",
                               "--seconds", "30"], stderr=subprocess.PIPE, text=True)
    try:
        cli("run", "-q", BLUEPRINT / "config.toml", "--out", tmp_path / "live",
            "--set", "episode.duration=3.0", "--set", f'modules.uav.params.listen="127.0.0.1:{port}"',
            "--set", "modules.comm.params.raytracing.samples_per_src=10000", check=0)
    finally:
        sender.terminate()
        sender.wait(timeout=10)
    status = json.loads((tmp_path / "live" / "run.json").read_text())
    assert status["status"] == "completed" and status["pacing"]["pace"] == 1.0
    log = caviar.load_run(tmp_path / "live")
    positions = [m.data for m in log.decoded("3D.mobility.positions")]
    assert positions and {p["UE_Id"] for p in positions} == {"uav1"}
    # Every position on the vehicle's route (within the float32 of MAVLink), and moving.
    route = read_waypoints(DATA / "central_park_path0_scene.csv")
    xyz = np.array([[p["position"][k] for k in "xyz"] for p in positions])
    assert max(_distance_to_polyline(q, route) for q in xyz) < 0.01
    assert np.linalg.norm(xyz[-1] - xyz[0]) > 5.0
    assert all(p["age_s"] < 1.0 for p in positions)
    predictions = [m.data for m in log.decoded("communications.prediction")]
    assert len(predictions) == len(positions)
    assert [p["horizon_s"] for p in predictions[-1]["predictions"]] == [0.5, 1.0, 2.0]
    assert {p["source"] for p in predictions[-1]["predictions"]} == {"constant-velocity"}
    telemetry = [m.data for m in log.decoded("live.telemetry")][-1]
    assert telemetry["received"] > 20 and telemetry["garbage"] == 0
