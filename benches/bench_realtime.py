"""Benchmark of the live twin (issue #25): late steps at wall-clock pace, prediction error
by horizon, and the latency from a MAVLink message's arrival to the prediction made from it.

- ``late_steps``: 1 and 5 UAVs (waypoint-flight, spread along the Central Park route)
  with Sionna RT in the loop (sionna-link, shoot cache, ``uav_mesh = false``,
  predictions at 0.5/1/2 s), ``pace = 1.0``, Ts = 0.5 s: run.json's pacing report.
- ``path_gain_error_db``: the same flights unpaced, predictions from the flight plan
  (``forecast``) and without it (``constant-velocity``), against the link computed later
  (:func:`caviar_plugins.radio.prediction.prediction_errors`).
- ``latency_ms``: a pymavlink sender in another process streams a UAV's positions
  (LOCAL_POSITION_NED at 20 Hz, stamped with their send time) to ``mavlink-telemetry``
  at pace 1.0; a probe module in the last stage notes the wall clock (CLOCK_MONOTONIC,
  shared by the processes) when the prediction made from a message's position reaches it:
  p50 and p99 of send (= arrival, on localhost) → prediction published. It includes the
  wait for the next step (the newest message is at most 50 ms old when a step takes it).

Writes ``docs/results/realtime.json`` with the machine. Not a test: it takes minutes.

    .venv/bin/python benches/bench_realtime.py [--duration 30] [--samples 100000]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import pathlib
import socket
import tempfile
import time

import numpy as np

import caviar
from bench_perf_steps import machine
from bench_scaling import ROUTE
from caviar_plugins import DATA
from caviar_plugins.mobility import Path, read_waypoints
from caviar_plugins.radio.prediction import prediction_errors

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "realtime.json"
TS = 0.5
HORIZONS = [0.5, 1.0, 2.0]


def flight_config(n: int, duration: float, samples: int, pace: float | None, forecast: int) -> str:
    length = Path(read_waypoints(DATA / ROUTE)).length
    text = f"""
[episode]
ts = {TS}
duration = {duration}
seed = 1
stages = ["mobility", "communications"]
{f"pace = {pace}" if pace else ""}
"""
    for i in range(n):
        text += f"""
[modules.uav{i + 1}]
stage = "mobility"
plugin = "waypoint-flight"
[modules.uav{i + 1}.params]
waypoints = "{(DATA / ROUTE).as_posix()}"
frame = "scene"
ue_id = "uav{i + 1}"
end_at_last = false
start_m = {i * length / n:.1f}
forecast_steps = {forecast}
"""
    text += f"""
[modules.comm]
stage = "communications"
plugin = "sionna-link"
[modules.comm.params]
raytracing = {{ samples_per_src = {samples}, threads = 1 }}
publish_channels = false
uav_mesh = false
predict_horizons_s = {HORIZONS}
warm_up_ues = {n * (1 + len(HORIZONS))}
"""
    return text


MAVLINK_PORT = 14561
SENDER_HZ = 20.0


def _sender(port: int, seconds: float, start: list[float], velocity: list[float]) -> None:
    """Another process: LOCAL_POSITION_NED at SENDER_HZ along a straight line, stamped
    with its send time (time_boot_ms = CLOCK_MONOTONIC in ms, shared by the processes)."""
    from pymavlink.dialects.v20 import all as mavlink

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = time.monotonic()
    k = 0
    while (now := time.monotonic()) - t0 < seconds:
        e, n, u = (start[i] + velocity[i] * (now - t0) for i in range(3))
        msg = mav.local_position_ned_encode(int(now * 1e3) & 0xFFFFFFFF, n, e, -u, velocity[1], velocity[0],
                                            -velocity[2])
        sock.sendto(msg.pack(mav), ("127.0.0.1", port))
        mav.seq = (mav.seq + 1) % 256
        k += 1
        time.sleep(max(0.0, t0 + k / SENDER_HZ - time.monotonic()))


class LatencyProbe(caviar.Plugin):
    """The last stage: when a UE's prediction reaches it, the wall clock (monotonic ms)
    minus the send time of the MAVLink message its position came from; written to
    ``out`` (JSON) at teardown."""

    subscribe = ["3D.mobility.positions", "communications.prediction"]

    @dataclasses.dataclass
    class Params:
        out: str = ""

    def setup(self, ctx):
        self.latencies: list[float] = []
        self.out = pathlib.Path(ctx.params.out)

    def step(self, t, inbox):
        now_ms = time.monotonic() * 1e3
        sent = {m.data["UE_Id"]: m.data["time_boot_ms"] for m in inbox.on("3D.mobility.positions")
                if "time_boot_ms" in m.data}
        for m in inbox.on("communications.prediction"):
            if m.data["UE_Id"] in sent:
                self.latencies.append((now_ms - sent[m.data["UE_Id"]]) % 2**32)
        return []

    def teardown(self):
        self.out.write_text(json.dumps(self.latencies))


def latency_config(duration: float, samples: int, out: pathlib.Path, start: list[float]) -> str:
    return f"""
[episode]
ts = {TS}
duration = {duration}
seed = 1
stages = ["mobility", "communications", "probe"]
pace = 1.0

[modules.uav]
stage = "mobility"
plugin = "mavlink-telemetry"
[modules.uav.params]
listen = "127.0.0.1:{MAVLINK_PORT}"
systems = {{ 1 = "uav1" }}
source = "local"

[modules.comm]
stage = "communications"
plugin = "sionna-link"
[modules.comm.params]
raytracing = {{ samples_per_src = {samples}, threads = 1 }}
publish_channels = false
uav_mesh = false
predict_horizons_s = {HORIZONS}
warm_up_ues = {1 + len(HORIZONS)}

[modules.probe]
stage = "probe"
plugin = "bench_realtime:LatencyProbe"
params = {{ out = "{out.as_posix()}" }}
"""


def latency(duration: float, samples: int, tmp_path: pathlib.Path) -> dict:
    """A MAVLink sender streams a UAV flying east at 10 m/s at 40 m; the run follows it
    at pace 1.0 and predicts its link: arrival → prediction latency, p50 and p99."""
    route = read_waypoints(DATA / ROUTE)
    start = [float(route[0][0]), float(route[0][1]), 40.0]
    out = tmp_path / "latency.json"
    sender = multiprocessing.get_context("spawn").Process(
        target=_sender, args=(MAVLINK_PORT, duration + 30.0, start, [10.0, 0.0, 0.0]), daemon=True)
    sender.start()
    try:
        status, log = run(latency_config(duration, samples, out, start), tmp_path / "live")
    finally:
        sender.terminate()
    ms = np.array(json.loads(out.read_text()))
    telemetry = [m.data for m in log.decoded("live.telemetry")][-1]
    return {"n": int(ms.size), "p50": round(float(np.percentile(ms, 50)), 1),
            "p99": round(float(np.percentile(ms, 99)), 1), "max": round(float(ms.max()), 1),
            "sender_hz": SENDER_HZ, "pacing": status["pacing"],
            "telemetry": {k: telemetry[k] for k in ("received", "missing", "late", "garbage")}}


def run(text: str, out: pathlib.Path) -> tuple[dict, caviar.RunLog]:
    cfg = out.with_suffix(".toml")
    cfg.write_text(text)
    log = caviar.Simulation.from_toml(cfg, out=out).run()
    return json.loads((out / "run.json").read_text()), log


def errors_of(log) -> dict:
    predictions = [m.data for m in log.decoded("communications.prediction")]
    errors = prediction_errors(predictions, [(m.time, m.data) for m in log.decoded("communications.link")])
    return {str(h): {"n": e["n"], "mean_abs_db": round(e["path_gain_error_db"]["mean_abs"], 3),
                     "p95_abs_db": round(e["path_gain_error_db"]["p95_abs"], 3),
                     "same_best_pair": round(e["same_best_pair"], 3),
                     "los_transitions": e["los_transitions"], "los_transitions_caught": e["los_transitions_caught"]}
            for h, e in errors.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=30.0, help="virtual seconds per run")
    ap.add_argument("--samples", type=int, default=100_000, help="rays per source")
    args = ap.parse_args()
    result: dict = {"ts_s": TS, "horizons_s": HORIZONS, "duration_s": args.duration, "samples_per_src": args.samples}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = pathlib.Path(tmp)
        late = {}
        for n in (1, 5):
            status, _ = run(flight_config(n, args.duration, args.samples, 1.0, 4), tmp_path / f"paced{n}")
            late[f"{n}uav"] = status["pacing"]
            print(f"{n} UAV(s) at pace 1.0:", status["pacing"], "RTF", status["rtf"], flush=True)
        result["late_steps"] = {k: v["late_steps"] for k, v in late.items()}
        result["pacing"] = late
        for name, forecast in (("forecast", 4), ("constant-velocity", 0)):
            _, log = run(flight_config(1, args.duration, args.samples, None, forecast), tmp_path / name)
            result.setdefault("prediction", {})[name] = errors_of(log)
            print(name, result["prediction"][name], flush=True)
        result["path_gain_error_db"] = {h: e["mean_abs_db"] for h, e in result["prediction"]["forecast"].items()}
        result["path_gain_error_db_constant_velocity"] = {
            h: e["mean_abs_db"] for h, e in result["prediction"]["constant-velocity"].items()}
        lat = latency(args.duration, args.samples, tmp_path)
        print("latency", lat, flush=True)
        result["latency_ms"] = {k: lat[k] for k in ("p50", "p99")}
        result["latency"] = lat
    result["targets"] = {"latency_p99_ms": TS * 1e3, "late_steps_1uav": 0, "path_gain_error_db_1s": 1.0}
    result["machine"] = machine()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("latency_ms", "late_steps", "path_gain_error_db")}))


if __name__ == "__main__":
    main()
