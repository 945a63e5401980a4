"""The mavlink-telemetry plugin against a real MAVLink sender.

A sender process (spawned, pymavlink) streams scripted MAVLink over UDP on localhost:
positions along a known trajectory, packets it drops (their sequence numbers skipped),
packets it holds back and sends later, duplicates, garbage, a stranger's system ID, and
silence. The plugin runs inside a caviar Simulation, stepped by the test with short
sleeps (it never waits for telemetry: each step takes what arrived), or its decoder and
UDP reader are driven directly for the exact counts. Projections are checked against
pyproj independently of the plugin's code.
"""

import json
import math
import multiprocessing
import socket
import time

import pytest

import caviar
from caviar.runlog import load_run
from configs import episode, module
from conftest import write_config

pytest.importorskip("pymavlink")

from caviar_plugins.live.geo import EnuFrame  # noqa: E402
from caviar_plugins.live.mavlink_telemetry import Converter, MavlinkTelemetry  # noqa: E402
from caviar_plugins.live.telemetry import TelemetryDecoder, UdpReader  # noqa: E402
from caviar_plugins.schema import LIVE_TELEMETRY, POSITIONS  # noqa: E402

# -- the sender (another process) ------------------------------------------------------


def _sender_main(conn):
    """Runs scripts sent over ``conn`` as ``(host, port, ops)`` until None; replies with
    the number of datagrams sent. Ops:

    ``("local", sysid, time_boot_ms, x, y, z[, vx, vy, vz])`` / ``("global", sysid,
    time_boot_ms, lat_e7, lon_e7, alt_mm, relative_alt_mm[, vx, vy, vz (cm/s)])``: one
    packet (sequence number + 1; velocity 0 unless given); wrapped as
    ``("drop", op)`` it is packed (its sequence number used) but not sent, ``("hold", op)``
    kept until ``("release",)``, ``("again",)`` resends the last datagram, ``("junk", b,
    op)`` sends ``b`` and the packet in one datagram; ``("raw", b)``, ``("sleep", s)``.
    """
    from pymavlink.dialects.v20 import all as mavlink

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    encoders: dict = {}
    conn.send("ready")

    def packet(op):
        kind, sysid, ms, *v = op
        mav = encoders.setdefault(sysid, mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1))
        if kind == "local":
            msg = mav.local_position_ned_encode(ms, v[0], v[1], v[2], *(v[3:6] or (0.0, 0.0, 0.0)))
        else:
            msg = mav.global_position_int_encode(ms, v[0], v[1], v[2], v[3], *(v[4:7] or (0, 0, 0)), 0)
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        return buf

    while (job := conn.recv()) is not None:
        host, port, ops = job
        held: list = []
        last, sent = b"", 0
        for op in ops:
            out = _datagram(op, packet, held, last)
            if out is not None:
                sock.sendto(out, (host, port))
                last, sent = out, sent + 1
        conn.send(sent)
    sock.close()


def _datagram(op, packet, held, last):
    """What one op of a script sends (None: nothing)."""
    kind = op[0]
    if kind == "sleep":
        time.sleep(op[1])
        return None
    if kind == "drop":
        packet(op[1])
        return None
    if kind == "hold":
        held.append(packet(op[1]))
        return None
    if kind == "raw":
        return op[1]
    if kind == "release":
        return held.pop(0)
    if kind == "again":
        return last
    if kind == "junk":
        return op[1] + packet(op[2])
    return packet(op)


class Sender:
    def __init__(self):
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with the core's threads
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_sender_main, args=(child,), daemon=True)
        self.proc.start()
        assert self.conn.poll(60) and self.conn.recv() == "ready", "the sender process did not start"
        self.busy = False

    def start(self, address: str, ops) -> None:
        host, port = address.rsplit(":", 1)
        self.conn.send((host, int(port), ops))
        self.busy = True

    def done(self) -> int | None:
        """Datagrams sent by the script once it has finished, else None."""
        if self.busy and self.conn.poll():
            self.busy = False
            return self.conn.recv()
        return None

    def wait(self, timeout: float = 20.0) -> int:
        assert self.conn.poll(timeout), "the sender did not finish its script"
        self.busy = False
        return self.conn.recv()

    def close(self):
        self.conn.send(None)
        self.proc.join(5)


@pytest.fixture(scope="module")
def sender():
    s = Sender()
    yield s
    s.close()


def _pyproj():
    return pytest.importorskip("pyproj")


# -- conversions ---------------------------------------------------------------------


class _Msg:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def test_conversions_ned_enu_and_altitude():
    """NED to the scene frame; the tangent plane against PROJ's topocentric conversion
    (independent of the plugin's formulas) within 1 mm over 2 km; both altitude modes."""
    ned = Converter("local", [10.0, 20.0, 1.5])
    assert ned(_Msg(x=3.0, y=-4.0, z=-7.0)) == (6.0, 23.0, 8.5)  # x east = y_ned, y north = x_ned, z = -z_ned
    assert ned.velocity(_Msg(vx=1.0, vy=2.0, vz=-0.5)) == (2.0, 1.0, 0.5)

    pyproj = _pyproj()
    lat0, lon0 = 40.7812, -73.9665  # an origin for central_park (any place will do)
    topo = pyproj.Transformer.from_pipeline(
        f"+proj=pipeline +step +proj=cart +ellps=WGS84 +step +proj=topocentric +ellps=WGS84 "
        f"+lat_0={lat0} +lon_0={lon0} +h_0=0")
    frame = EnuFrame(lat0, lon0)
    for dlat, dlon in [(0.0, 0.0), (0.01, 0.0), (0.0, -0.02), (-0.012, 0.017), (0.015, 0.015)]:
        lat, lon = lat0 + dlat, lon0 + dlon
        e, n, _ = topo.transform(lon, lat, 0.0)
        x, y = frame.to_xy(lat, lon)
        assert math.hypot(x - e, y - n) < 1e-3, (lat, lon, x, y, e, n)
    g = Converter("global", [0.0, 0.0, 2.0], frame, "relative")
    m = _Msg(lat=int(round(lat0 * 1e7)), lon=int(round(lon0 * 1e7)), alt=130_000, relative_alt=25_000)
    assert g(m) == pytest.approx((0.0, 0.0, 27.0), abs=0.01)
    amsl = Converter("global", [0.0, 0.0, 0.0], frame, "amsl", alt0=100.0)
    assert amsl(m)[2] == pytest.approx(30.0)
    assert g(_Msg(lat=0, lon=0, alt=0, relative_alt=0)) is None  # no fix
    assert g.velocity(_Msg(vx=150, vy=-20, vz=30)) == pytest.approx((-0.2, 1.5, -0.3))  # cm/s north, east, down


# -- counting, with the reader driven directly ----------------------------------------


def _drive(reader: UdpReader, sender: Sender, ops, timeout: float = 15.0) -> int:
    sender.start(reader.address, ops)
    sent = sender.wait(timeout)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with reader.lock:
            if reader.decoder.counts["datagrams"] >= sent:
                return sent
        time.sleep(0.01)
    raise AssertionError(f"the reader got {reader.decoder.counts['datagrams']} of {sent} datagrams")


def test_counts_drops_delays_duplicates_garbage_and_strangers(sender):
    """Exact counts: 60 positions 20 ms apart (vehicle clock) with three dropped, two held
    back (one by 3 packets, 60 ms: late; one by 1 packet, 20 ms: within the 50 ms
    tolerance), one sent twice, garbage of three kinds and a stranger (system 7)."""
    from pymavlink.dialects.v20 import all as mavlink

    decoder = TelemetryDecoder({1: "uav1"}, "local", Converter("local", [0.0, 0.0, 0.0]),
                               late_tolerance_s=0.05)
    reader = UdpReader(decoder, "127.0.0.1", 0).start()
    try:
        def pos(i):
            return ("local", 1, 1000 + 20 * i, 2.0 * i, -1.0 * i, -10.0 - 0.1 * i)

        junk = bytes(range(0x20, 0x7F))  # no 0xFD / 0xFE: a single run of garbage
        other = mavlink.MAVLink(None, srcSystem=1, srcComponent=99)  # its own sequence numbers
        corrupt = bytearray(other.local_position_ned_encode(0, 1.0, 2.0, 3.0, 0, 0, 0).pack(other))
        corrupt[12] ^= 0xFF  # a payload byte: bad CRC
        cut = other.local_position_ned_encode(0, 1.0, 2.0, 3.0, 0, 0, 0).pack(other)[:15]
        ops: list = []
        for i in range(60):
            if i in (10, 11, 30):
                ops.append(("drop", pos(i)))
            elif i in (20, 40):
                ops.append(("hold", pos(i)))
            elif i == 5:
                ops.append(("junk", b"\x00\x01\x02", pos(i)))  # garbage before a good packet, one datagram
            else:
                ops.append(pos(i))
            if i in (23, 41):
                ops.append(("release",))
            if i == 50:
                ops.append(("again",))
            if i == 45:
                ops += [("raw", junk), ("raw", bytes(corrupt)), ("raw", cut),
                        ("local", 7, 5000, 0.0, 0.0, 0.0), ("local", 7, 5020, 0.0, 0.0, 0.0)]
            ops.append(("sleep", 0.002))
        sent = _drive(reader, sender, ops)
        assert sent == 60 - 3 + 1 + 5  # datagrams: held ones sent late, drops never
        with reader.lock:
            snap = decoder.snapshot(time.monotonic())
        c = snap.counts
        assert c["missing"] == 3  # 10, 11, 30: 20 and 40 came after all
        assert c["out_of_order"] == 2
        assert c["late"] == 1  # 20, released 60 ms of vehicle time behind; 40 only 20 ms
        assert c["duplicate"] == 1
        assert c["received"] == 57 + 1
        assert c["positions"] == 55  # neither held packet, nor the duplicate, replaced a newer one
        assert c["garbage"] == 4 and c["garbage_bytes"] == 3 + len(junk) + len(corrupt) + len(cut)
        assert c["unknown_system"] == 2 and c["unknown_message"] == 0
        [(ue, sysid, sample, age)] = snap.positions
        assert (ue, sysid, sample.time_boot_ms) == ("uav1", 1, 1000 + 20 * 59)
        assert sample.xyz == pytest.approx((-59.0, 118.0, 10.0 + 5.9))  # (y_ned, x_ned, -z_ned)
        warnings = [e for e in snap.events if e.startswith("warning")]
        assert len(warnings) == 2, snap.events  # garbage once, system 7 once
        assert any("system 7" in w for w in warnings) and any("garbage" in w for w in warnings)
    finally:
        reader.close()


# -- in a Simulation -----------------------------------------------------------------

CONFIG = (episode(0.05, ["mobility"], steps=2000, seed=1)
          + module("uav", "mobility", "mavlink-telemetry", {"listen": "127.0.0.1:0"}, params_table=True))


def _status(msgs):
    [s] = [m.data for m in msgs if m.topic == LIVE_TELEMETRY]
    return s


def _steps_until(sim, sender, condition, timeout=15.0, pause=0.02):
    """Steps (pausing between steps) until the sender (if any) is done and
    ``condition(status)``; returns the steps' messages."""
    out, done, deadline = [], sender is None, time.monotonic() + timeout
    while time.monotonic() < deadline:
        msgs = sim.step()
        out.append(msgs)
        done = done or sender.done() is not None
        if done and condition(_status(msgs)):
            return out
        time.sleep(pause)
    raise AssertionError(f"timed out; last status {_status(out[-1])}")


def _trajectory(ms: int) -> tuple[float, float, float]:
    t = (ms - 5000) / 1000
    return (-120.0 + 30.0 * t, 40.0 + 15.0 * math.sin(t), 25.0 + 2.0 * t)


def _velocity(ms: int) -> tuple[float, float, float]:
    t = (ms - 5000) / 1000
    return (30.0, 15.0 * math.cos(t), 2.0)


def test_run_follows_a_streamed_trajectory_through_the_scene_projection(tmp_path, sender):
    """GLOBAL_POSITION_INT at 50 Hz for 1.5 s along a known scene trajectory, geodetic by
    the scene.json's PROJ string (pyproj's inverse, in the test): every step publishes the
    newest position, in order, within 1 cm horizontally (1e-7 degree quantisation) and
    1 mm vertically of where the vehicle was at its time_boot_ms, with its velocity (NED
    cm/s to the scene frame); nothing missing."""
    pyproj = _pyproj()
    from caviar_plugins.osm.frame import proj_string

    lat0, lon0 = 60.1715, 24.94425
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.json").write_text(json.dumps({"origin": {"lat": lat0, "lon": lon0},
                                                  "proj": proj_string(lat0, lon0)}))
    inverse = pyproj.Transformer.from_crs(proj_string(lat0, lon0), "EPSG:4326", always_xy=True)
    ops: list = []
    n = 75
    for i in range(n):
        ms = 5000 + 20 * i
        x, y, z = _trajectory(ms)
        lon, lat = inverse.transform(x, y)
        ve, vn, vu = _velocity(ms)
        ops += [("global", 1, ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((50 + z) * 1000)),
                 int(round(z * 1000)), round(vn * 100), round(ve * 100), round(-vu * 100)), ("sleep", 0.02)]
    cfg = write_config(tmp_path, CONFIG + 'source = "global"\nscene = "scene"\n')
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "run") as sim:
        first = sim.step()
        assert [m.topic for m in first] == [LIVE_TELEMETRY]  # no position before the first fix
        sender.start(_status(first)["listen"], ops)
        t0 = time.monotonic()
        steps = _steps_until(sim, sender, lambda s: s["positions"] == n)
        wall = time.monotonic() - t0
    published = [m.data for msgs in steps for m in msgs if m.topic == POSITIONS]
    assert len(published) >= 10 and all(p["UE_Id"] == "uav1" and p["UE_type"] == "UAV" for p in published)
    times = [p["time_boot_ms"] for p in published]
    assert times == sorted(times) and times[-1] == 5000 + 20 * (n - 1)
    assert len(set(times)) >= 10, f"only {len(set(times))} distinct positions in {wall:.1f} s"
    for p in published:
        x, y, z = _trajectory(p["time_boot_ms"])
        q = p["position"]
        assert math.hypot(q["x"] - x, q["y"] - y) < 0.01 and abs(q["z"] - z) < 1e-3, (p, (x, y, z))
        v = p["velocity"]
        assert [v["x"], v["y"], v["z"]] == pytest.approx(_velocity(p["time_boot_ms"]), abs=0.006)  # cm/s
        assert 0 <= p["age_s"] < 5.0
    status = _status(steps[-1])
    assert {k: status[k] for k in ("received", "positions", "missing", "late", "out_of_order", "garbage",
                                   "unknown_system")} == {"received": n, "positions": n, "missing": 0, "late": 0,
                                                          "out_of_order": 0, "garbage": 0, "unknown_system": 0}
    # Recorded like any mobility plugin's positions (the extra fields as columns).
    log = load_run(tmp_path / "run")
    recorded = log.topic(POSITIONS)
    assert recorded.height == len(published) and recorded["time_boot_ms"].to_list() == times
    assert "age_s" in recorded.columns


def test_garbage_a_stranger_and_silence_warn_and_hold_the_last_position(tmp_path, sender, capfd):
    """Garbage and an unexpected system ID: a warning each, no crash. Silence: a warning
    once per outage, the last position held with a growing age_s; positions again after."""
    cfg = write_config(tmp_path, CONFIG + "stale_s = 0.3\n")
    burst = [op for i in range(10)
             for op in (("local", 1, 1000 + 20 * i, 1.0 * i, 2.0, -30.0, 0.5, 0.25, -1.0), ("sleep", 0.01))]
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "run") as sim:
        address = _status(sim.step())["listen"]
        sender.start(address, burst + [("raw", b"\x00garbage\x01" * 5), ("local", 9, 1, 0.0, 0.0, 0.0)])
        _steps_until(sim, sender, lambda s: s["positions"] == 10 and s["unknown_system"] == 1)
        # Silence: the last position (x_ned 9 -> y = 9, y_ned 2 -> x = 2, z = 30) is held.
        held = _steps_until(sim, None, lambda s: s["ues"][0]["age_s"] > 0.9, pause=0.05)
        positions = [m.data for msgs in held for m in msgs if m.topic == POSITIONS]
        assert all(p["position"] == {"x": 2.0, "y": 9.0, "z": 30.0} for p in positions)
        assert all(p["velocity"] == {"x": 0.25, "y": 0.5, "z": 1.0} for p in positions)
        ages = [p["age_s"] for p in positions]
        assert ages == sorted(ages) and ages[-1] > ages[0] + 0.5 and len(ages) >= 5
        assert _status(held[-1])["ues"] == [{"UE_Id": "uav1", "sysid": 1, "age_s": ages[-1], "stale": True,
                                              "positions": 10}]
        # Back, then silent again: a second warning.
        sender.start(address, [("local", 1, 2000 + 20 * i, 50.0, 2.0, -30.0) for i in range(3)])
        back = _steps_until(sim, sender, lambda s: s["positions"] == 13)
        assert not _status(back[-1])["ues"][0]["stale"]
        _steps_until(sim, None, lambda s: s["ues"][0]["stale"], pause=0.05)
    err = capfd.readouterr().err
    warnings = [line for line in err.splitlines() if "warning:" in line]
    assert sum("garbage" in w for w in warnings) == 1
    assert sum("ignoring MAVLink system 9" in w for w in warnings) == 1
    assert sum("no LOCAL_POSITION_NED from system 1 (uav1) for" in w for w in warnings) == 2, err
    assert sum("positions again after" in line for line in err.splitlines()) == 1
    assert "13 positions used" in err  # the summary at teardown
    assert load_run(tmp_path / "run").status["status"] == "completed"


def test_config_errors_name_the_parameter(tmp_path):
    for params, key, words in [
        ('source = "global"\n', "source", "origin = [lat, lon, alt]"),
        ('source = "global"\nscene = "central_park"\n', "scene", "no scene.json"),
        ('source = "global"\norigin = [40.78, -73.97]\naltitude = "amsl"\n', "altitude", "altitude AMSL"),
        ('systems = { uav = "uav1" }\n', "systems", "system IDs 1..255"),
        ('stale_s = 0.0\n', "stale_s", "expected > 0 seconds"),
        ('late_tolerance_s = -1.0\n', "late_tolerance_s", "expected >= 0 seconds"),
    ]:
        cfg = write_config(tmp_path, CONFIG + params)
        with pytest.raises(caviar.ConfigError) as e:
            caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
        assert f"params.{key}" in str(e.value) and words in str(e.value), str(e.value)
    cfg = write_config(tmp_path, CONFIG.replace('"127.0.0.1:0"', '"14550"'))
    with pytest.raises(caviar.ConfigError, match=r"params\.listen: expected HOST:PORT"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    assert MavlinkTelemetry.Params().system_ids == {1: "uav1"}
