"""The ``mavlink-telemetry`` mobility plugin: a real vehicle (or its simulator) in the loop.

It listens for MAVLink (the protocol of PX4 and ArduPilot) on UDP and publishes, every
step, where each followed vehicle is, in the paper's schema on ``3D.mobility.positions``::

    {"UE_type": "UAV", "UE_Id": "uav1", "position": {"x": …, "y": …, "z": …},
     "velocity": {"x": …, "y": …, "z": …}, "age_s": 0.04, "time_boot_ms": 81240, "sysid": 1}

``velocity`` is the vehicle's own (m/s, scene frame, from the same message, as
sumo-traffic's), ``age_s`` how long ago (wall clock) the position arrived,
``time_boot_ms`` the vehicle's timestamp of it and ``sysid`` its MAVLink system ID
(consumers that read ``position`` alone, such as
:func:`caviar_plugins.schema.read_position`, ignore the rest).
A vehicle is published from its first position on, once per step: its newest position
(by ``time_boot_ms``), however many arrived since the previous step. When none has
arrived for ``stale_s`` it says so (a warning once per outage) and keeps publishing the
last one, whose ``age_s`` grows.

**Never waiting.** A background thread reads the socket and parses each datagram as it
arrives (pymavlink, :mod:`caviar_plugins.live.telemetry`), stamping it with the wall
clock; a step only takes the newest positions under a lock. So a step never waits for
telemetry, the arrival times are exact whatever the step rate, and nothing queues up in
the kernel while a slow step (a ray trace) runs. The engine's virtual time and the
vehicle's clock are not tied together: pace the run on the wall clock (``pace = 1.0``
in ``[episode]``), or run it as fast as possible and read ``age_s``. A live run is not reproducible; its recording is.

**Topics.** Publishes ``3D.mobility.positions`` (above) and ``live.telemetry``, once per
step::

    {"listen": "127.0.0.1:14550", "new_positions": 5, "datagrams": …, "received": …,
     "positions": …, "late": …, "out_of_order": …, "duplicate": …, "missing": …,
     "garbage": …, "garbage_bytes": …, "unknown_system": …, "unknown_message": …,
     "no_fix": …, "restarts": …,
     "ues": [{"UE_Id": "uav1", "sysid": 1, "age_s": 0.04, "stale": false, "positions": 412}],
     "events": ["warning: …"]}

the counts since the start (:data:`caviar_plugins.live.telemetry.COUNTS` defines each:
``missing`` from gaps in the MAVLink sequence numbers, ``late`` from ``time_boot_ms``
older than the newest by more than ``late_tolerance_s``, ``garbage`` for bytes that are
not MAVLink or fail the CRC) and the warnings of the step, which also go to stderr. At
the end a summary of the counts goes to stderr. Subscribes to nothing.

**Params.**

* ``listen = "127.0.0.1:14550"``: UDP address to listen on (localhost only by default;
  ``"0.0.0.0:14550"`` for a vehicle on the network; port 0: any free port, reported in
  ``live.telemetry``).
* ``systems = {1 = "uav1"}``: MAVLink system ID -> ``UE_Id`` of each vehicle followed.
  A packet from another system ID is ignored, with a warning once per system ID.
* ``ue_type = "UAV"``: the payloads' ``UE_type`` (``"UAV"``, as waypoint-flight's).
* ``source = "local"``: which message gives the position: ``"local"``
  (LOCAL_POSITION_NED) or ``"global"`` (GLOBAL_POSITION_INT, needs ``scene`` or
  ``origin``). Position messages of the other kind are counted as received, not used.
* ``scene = ""``: for ``global``, a scene built by ``caviar-core scene build`` (its folder,
  ``scene.xml`` or ``scene.json``): its ``scene.json`` holds the PROJ string of its frame.
* ``origin = []``: for ``global`` with a scene that has no ``scene.json`` (the shipped
  ``central_park``): ``[lat, lon, alt]``, the WGS84 point at the scene's (0, 0, 0) and
  its altitude AMSL (m). With ``scene``, only to add the altitude (lat, lon as its own).
* ``altitude = "relative"``: for ``global``, z = ``relative_alt`` (height above the
  vehicle's home) + ``offset`` z; ``"amsl"``: z = ``alt`` - the origin's altitude.
* ``offset = [0, 0, 0]``: added to every position (m, scene frame): where the local
  NED origin (the vehicle's EKF origin, usually its home) lies in the scene, or the
  height of the home above the scene's ground.
* ``stale_s = 2.0``: wall-clock seconds without a new position before the warning.
* ``late_tolerance_s = 0.05``: a position older than the newest by more than this is late.
* ``restart_s = 10.0``: ``time_boot_ms`` going back by more than this is a reboot.

**Conversions** (scene frame: x east, y north, z up, metres).

* LOCAL_POSITION_NED (x north, y east, z down, from the EKF origin):
  x = y_ned + offset x, y = x_ned + offset y, z = -z_ned + offset z; velocity
  (vy, vx, -vz).
* GLOBAL_POSITION_INT (lat, lon in 1e-7 degrees, WGS84; ``alt`` AMSL and
  ``relative_alt`` in mm): x, y through the scene's projection (``scene.json``'s PROJ
  string with pyproj, else the local tangent plane (ENU) at ``origin``;
  :mod:`caviar_plugins.live.geo`), z as ``altitude`` says; then + offset; velocity
  (vy, vx, -vz) / 100 (cm/s north, east, down; grid north is taken as true north, which
  it is at the scene's origin). Latitude and longitude both 0 means no fix: not used
  (counted as ``no_fix``).

**Pointing a simulator at it.** The plugin only listens: it sends no heartbeat and
requests no streams, so the vehicle (or a MAVLink router) must already send to it.

* PX4 SITL (``make px4_sitl gz_x500``) sends its ground-station link to UDP 14550 on
  localhost, the ``udp://:14550`` that QGroundControl listens on: the defaults follow
  it. Its system ID is the parameter ``MAV_SYS_ID`` (1; instance N of a multi-vehicle
  SITL has N + 1): ``systems = {1 = "uav1", 2 = "uav2"}``. It streams both position
  messages; ``mavlink stream -u 18570 -s GLOBAL_POSITION_INT -r 20`` in the PX4 shell
  raises a rate on that link (its local port: 18570 + instance).
* ArduPilot SITL: ``sim_vehicle.py -v ArduCopter --out udp:127.0.0.1:14550`` (MAVProxy
  forwards the vehicle's stream there). Its system ID is ``SYSID_THISMAV`` (1); the
  rate of both position messages is ``SR0_POSITION`` (or MAVProxy's ``set streamrate``).
* Only one program can listen on a port: with QGroundControl open on 14550, have the
  vehicle or MAVProxy send a second stream elsewhere (``--out udp:127.0.0.1:14551``)
  and set ``listen`` to it.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import caviar
from caviar_plugins.live.geo import Frame, load_frame
from caviar_plugins.live.telemetry import TelemetryDecoder, UdpReader, dialect, parse_address
from caviar_plugins.schema import LIVE_TELEMETRY, POSITIONS, position_payload


def _systems(table: dict) -> dict[int, str]:
    out: dict[int, str] = {}
    for key, ue in table.items():
        try:
            sysid = int(key)
        except (TypeError, ValueError):
            sysid = -1
        if not 1 <= sysid <= 255:
            raise ValueError(f"systems: expected MAVLink system IDs 1..255 as keys, got {key!r}")
        if not isinstance(ue, str) or not ue:
            raise ValueError(f"systems.{key}: expected a UE_Id (a non-empty string), got {ue!r}")
        out[sysid] = ue
    if not out:
        raise ValueError("systems: expected at least one system ID -> UE_Id, e.g. {1 = \"uav1\"}")
    if len(set(out.values())) != len(out):
        raise ValueError(f"systems: two system IDs have the same UE_Id: {table}")
    return out


class Converter:
    """A position message (pymavlink) to scene coordinates; None when it has no fix."""

    def __init__(self, source: str, offset: list[float], frame: Frame | None = None, altitude: str = "relative",
                 alt0: float | None = None):
        self.source, self.frame, self.altitude = source, frame, altitude
        self.alt0 = 0.0 if alt0 is None else float(alt0)
        self.ox, self.oy, self.oz = (float(v) for v in offset)

    def __call__(self, m: Any) -> tuple[float, float, float] | None:
        if self.source == "local":
            return (m.y + self.ox, m.x + self.oy, -m.z + self.oz)
        if m.lat == 0 and m.lon == 0:
            return None
        assert self.frame is not None
        x, y = self.frame.to_xy(m.lat * 1e-7, m.lon * 1e-7)
        z = m.relative_alt / 1000 if self.altitude == "relative" else m.alt / 1000 - self.alt0
        return (x + self.ox, y + self.oy, z + self.oz)

    def velocity(self, m: Any) -> tuple[float, float, float]:
        """The message's velocity (north, east, down) in the scene frame, m/s."""
        scale = 1.0 if self.source == "local" else 0.01  # GLOBAL_POSITION_INT: cm/s
        return (m.vy * scale, m.vx * scale, -m.vz * scale)


class MavlinkTelemetry(caviar.Plugin):
    """Positions of real vehicles from MAVLink over UDP (see the module's docstring)."""

    publishes = (POSITIONS, LIVE_TELEMETRY)
    # Live input: the vehicle flew on while the run was down, so a resumed run listens again
    # and publishes what arrives from then on (the telemetry counts start again from zero).
    stateless = True

    @dataclasses.dataclass
    class Params:
        listen: str = "127.0.0.1:14550"
        """UDP HOST:PORT to listen on (localhost by default; 0.0.0.0 for the network)."""
        systems: dict = dataclasses.field(default_factory=lambda: {"1": "uav1"})
        """MAVLink system ID -> UE_Id, e.g. ``{1 = "uav1", 2 = "uav2"}``."""
        ue_type: str = "UAV"
        source: str = "local"
        """``local`` (LOCAL_POSITION_NED) or ``global`` (GLOBAL_POSITION_INT)."""
        scene: str = ""
        """global: a scene built by ``caviar-core scene build`` (folder, scene.xml or scene.json)."""
        origin: list[float] = dataclasses.field(default_factory=list)
        """global without scene.json: ``[lat, lon, alt]`` of the scene's (0, 0, 0)."""
        altitude: str = "relative"
        """global: ``relative`` (z = relative_alt + offset z) or ``amsl`` (z = alt - origin alt)."""
        offset: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
        """Added to every position (m): the local NED origin (or home height) in the scene."""
        stale_s: float = 2.0
        late_tolerance_s: float = 0.05
        restart_s: float = 10.0

        def __post_init__(self):
            parse_address(self.listen)
            self.system_ids = _systems(self.systems)
            if self.source not in ("local", "global"):
                raise ValueError(f"source: expected 'local' (LOCAL_POSITION_NED) or 'global' (GLOBAL_POSITION_INT), "
                                 f"got {self.source!r}")
            if self.altitude not in ("relative", "amsl"):
                raise ValueError(f"altitude: expected 'relative' or 'amsl', got {self.altitude!r}")
            if len(self.offset) != 3:
                raise ValueError(f"offset: expected [x, y, z] in metres, got {self.offset}")
            if not self.stale_s > 0:
                raise ValueError(f"stale_s: expected > 0 seconds, got {self.stale_s}")
            if not self.restart_s > 0:
                raise ValueError(f"restart_s: expected > 0 seconds, got {self.restart_s}")
            if not self.late_tolerance_s >= 0:
                raise ValueError(f"late_tolerance_s: expected >= 0 seconds, got {self.late_tolerance_s}")

    @staticmethod
    def converter(p: Any, config_dir) -> Converter:
        """The conversion the parameters ask for (ValueError naming the parameter if they
        cannot give one)."""
        if p.source == "local":
            return Converter("local", p.offset)
        if not p.scene and not p.origin:
            raise ValueError("source: 'global' needs the scene's geodetic frame: scene = a scene built by "
                             "`caviar-core scene build`, or origin = [lat, lon, alt]")
        frame, alt0 = load_frame(p.scene, p.origin, config_dir)
        if p.altitude == "amsl" and alt0 is None:
            raise ValueError("altitude: 'amsl' needs the altitude AMSL of the scene's z = 0: "
                             "origin = [lat, lon, alt]")
        return Converter("global", p.offset, frame, p.altitude, alt0)

    @classmethod
    def check_params(cls, params, config_dir):
        dialect()  # pymavlink installed?
        cls.converter(params, config_dir)

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        self.p = p
        self.convert = self.converter(p, ctx.config_dir)
        self.tag = f"{ctx.name} (mavlink-telemetry)"
        self.decoder = TelemetryDecoder(p.system_ids, p.source, self.convert, self.convert.velocity,
                                        stale_s=p.stale_s, late_tolerance_s=p.late_tolerance_s, restart_s=p.restart_s)
        host, port = parse_address(p.listen)
        self.reader = UdpReader(self.decoder, host, port).start()

    def step(self, t, inbox):
        snap = self.reader.snapshot()
        for e in snap.events:
            print(f"{self.tag}: t = {t:g} s: {e}", file=sys.stderr, flush=True)
        for ue_id, sysid, sample, age in snap.positions:
            msg = position_payload(ue_id, sample.xyz, self.p.ue_type)
            if sample.velocity is not None:
                msg["velocity"] = dict(zip("xyz", sample.velocity, strict=True))
            msg.update(age_s=round(age, 4), time_boot_ms=sample.time_boot_ms, sysid=sysid)
            yield POSITIONS, msg
        yield LIVE_TELEMETRY, {"listen": self.reader.address, "new_positions": snap.new_positions, **snap.counts,
                               "ues": snap.ues, "events": snap.events}

    def teardown(self):
        reader = getattr(self, "reader", None)
        if reader is None:
            return
        reader.close()
        with reader.lock:
            summary = self.decoder.summary()
        print(f"{self.tag}: {summary}", file=sys.stderr, flush=True)
