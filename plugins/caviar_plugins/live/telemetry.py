"""MAVLink telemetry in, counted: a decoder of UDP datagrams and the thread that reads them.

:class:`TelemetryDecoder` turns datagrams into the newest position of each followed
vehicle and counts what went wrong on the way (see :data:`COUNTS`); it does no I/O, so
tests and other transports can feed it directly. :class:`UdpReader` owns the UDP socket
and a background thread that feeds every datagram to the decoder as it arrives, stamped
with the wall clock (``time.monotonic``); the plugin takes a snapshot at each step under
the reader's lock, so a step never waits for the network.

Parsing is pymavlink's (the ``all`` dialect, MAVLink 1 and 2; signatures are not
checked) with ``robust_parsing``: bytes that are not MAVLink, packets with a bad CRC and
packets cut short come back as garbage, never as an exception. A datagram is parsed on
its own (MAVLink over UDP never splits a packet across datagrams), so garbage in one
cannot swallow the packets of the next.
"""

from __future__ import annotations

import dataclasses
import socket
import threading
import time
from typing import Any, Callable

POSITION_MESSAGES = {"global": "GLOBAL_POSITION_INT", "local": "LOCAL_POSITION_NED"}

COUNTS = ("datagrams", "received", "positions", "late", "out_of_order", "duplicate", "missing", "garbage",
          "garbage_bytes", "unknown_system", "unknown_message", "no_fix", "restarts")
"""What :attr:`TelemetryDecoder.counts` counts, from the start of the run:

* ``datagrams``: UDP datagrams read;
* ``received``: MAVLink packets (valid CRC) from a followed system, of any message type;
* ``positions``: position messages that became a UE's newest position;
* ``late``: position messages whose ``time_boot_ms`` was older than the newest already
  received from that system by more than the tolerance (never used as the position);
* ``out_of_order``: packets that arrived after a packet sent after them (MAVLink
  sequence number of a gap that arrived late; taken back out of ``missing``);
* ``duplicate``: packets whose sequence number was already seen (or is too old to place);
* ``missing``: packets never received, from the gaps in the sequence numbers of each
  sending component (gaps of 128 packets or more cannot be told from reordering);
* ``garbage`` / ``garbage_bytes``: pieces (and their bytes) that were not MAVLink, had a
  bad CRC or were cut short;
* ``unknown_system``: valid packets from a system ID not in ``systems`` (ignored);
* ``unknown_message``: packets of a message ID the dialect does not know (their CRC
  cannot be checked, so their header is not trusted either);
* ``no_fix``: GLOBAL_POSITION_INT at latitude = longitude = 0 (no position yet);
* ``restarts``: a system's ``time_boot_ms`` went back by more than ``restart_s`` (it
  rebooted): its clock and sequence numbers start over.
"""


def dialect() -> Any:
    """pymavlink's ``all`` dialect (MAVLink 2, which parses MAVLink 1 too)."""
    try:
        from pymavlink.dialects.v20 import all as mavlink
    except ImportError as e:
        raise ImportError(f"the MAVLink plugins need pymavlink: pip install 'caviar-plugins[live]' ({e})") from None
    return mavlink


@dataclasses.dataclass
class Sample:
    """A UE's newest position: scene coordinates, the vehicle's clock, when it came."""

    xyz: tuple[float, float, float]
    time_boot_ms: int
    received: float
    """``time.monotonic()`` when the datagram was read."""
    velocity: tuple[float, float, float] | None = None
    """m/s in the scene frame, as the vehicle reported it with the position."""


@dataclasses.dataclass
class Track:
    """What is known of one followed system."""

    ue_id: str
    sysid: int
    since: float
    """When it was last heard of (start, or its newest position): outages start here."""
    sample: Sample | None = None
    newest_ms: int | None = None
    positions: int = 0
    stale: bool = False
    other_types: set[str] = dataclasses.field(default_factory=set)


@dataclasses.dataclass
class _Sequence:
    last: int
    gaps: set[int] = dataclasses.field(default_factory=set)


@dataclasses.dataclass
class Snapshot:
    """What a step takes from the decoder."""

    positions: list[tuple[str, int, Sample, float]]
    """(UE_Id, system ID, newest sample, its age in seconds) of every UE with a position."""
    ues: list[dict[str, Any]]
    """Every followed UE: ``{"UE_Id", "sysid", "age_s" (None before its first position),
    "stale", "positions"}``."""
    counts: dict[str, int]
    new_positions: int
    """Positions accepted since the previous snapshot."""
    events: list[str]
    """Warnings and notes since the previous snapshot, oldest first."""


class TelemetryDecoder:
    """Datagrams in (:meth:`feed`), newest positions and counts out (:meth:`snapshot`).

    ``systems``: MAVLink system ID -> UE_Id of the vehicles followed. ``source``: which
    message gives the position (``"global"``: GLOBAL_POSITION_INT, ``"local"``:
    LOCAL_POSITION_NED); ``convert(msg)`` makes it scene coordinates (None: no fix) and
    ``velocity(msg)``, if given, its velocity in the scene frame (m/s).
    ``now`` is the start time on the clock of the ``now`` arguments (``time.monotonic``).
    Not thread-safe: :class:`UdpReader` calls it under its lock.
    """

    def __init__(self, systems: dict[int, str], source: str, convert: Callable[[Any], tuple | None],
                 velocity: Callable[[Any], tuple] | None = None, *,
                 stale_s: float = 2.0, late_tolerance_s: float = 0.05, restart_s: float = 10.0,
                 now: float | None = None, where: str = "UDP"):
        self.mavlink = dialect()
        self.systems = dict(systems)
        self.wanted = POSITION_MESSAGES[source]
        self.convert, self.velocity = convert, velocity
        self.stale_s, self.late_ms, self.restart_ms = stale_s, late_tolerance_s * 1000, restart_s * 1000
        self.where = where
        start = time.monotonic() if now is None else now
        self.tracks = {sysid: Track(ue, sysid, start) for sysid, ue in self.systems.items()}
        self.counts = dict.fromkeys(COUNTS, 0)
        self.events: list[str] = []
        self.new_positions = 0
        self._seqs: dict[tuple[int, int], _Sequence] = {}
        self._unknown_warned: set[int] = set()
        self._garbage_warned = False
        self._parser = self._new_parser()

    def _new_parser(self) -> Any:
        p = self.mavlink.MAVLink(None)
        p.robust_parsing = True
        return p

    # -- input -------------------------------------------------------------------------

    def feed(self, data: bytes, now: float) -> None:
        """One UDP datagram, read at ``now``."""
        self.counts["datagrams"] += 1
        try:
            msgs = self._parser.parse_buffer(data) or []
            left = self._parser.buf_len()
            if left:  # a packet cut short: its start is garbage
                self._garbage(left, "a datagram ended inside a MAVLink packet")
        except Exception as e:  # robust parsing raises none; a pymavlink surprise must not stop the reader
            msgs, left = [], len(data)
            self._garbage(len(data), f"pymavlink could not parse a datagram ({type(e).__name__}: {e})")
        if left:  # the next datagram starts afresh
            self._parser = self._new_parser()
        for m in msgs:
            self._handle(m, now)

    def _garbage(self, nbytes: int, why: str) -> None:
        self.counts["garbage"] += 1
        self.counts["garbage_bytes"] += nbytes
        if not self._garbage_warned:
            self._garbage_warned = True
            self.events.append(f"warning: garbage on {self.where}: {nbytes} bytes ({why}); ignored, and counted "
                               "as 'garbage' in live.telemetry from now on")

    def _handle(self, m: Any, now: float) -> None:
        if isinstance(m, self.mavlink.MAVLink_bad_data):
            self._garbage(len(m.data), str(m.reason))
            return
        if isinstance(m, self.mavlink.MAVLink_unknown):
            self.counts["unknown_message"] += 1
            return
        sysid, compid = m.get_srcSystem(), m.get_srcComponent()
        track = self.tracks.get(sysid)
        if track is None:
            self.counts["unknown_system"] += 1
            if sysid not in self._unknown_warned:
                self._unknown_warned.add(sysid)
                known = ", ".join(f"{s} -> {u}" for s, u in self.systems.items())
                self.events.append(f"warning: ignoring MAVLink system {sysid} on {self.where} ({m.get_type()}): not "
                                   f"in systems ({known}); add it there to follow it")
            return
        self.counts["received"] += 1
        kind = m.get_type()
        if kind in POSITION_MESSAGES.values() and track.newest_ms is not None \
                and m.time_boot_ms < track.newest_ms - self.restart_ms:
            self._restart(track, m.time_boot_ms)
        self._sequence((sysid, compid), m.get_seq())
        if kind == self.wanted:
            self._position(track, m, now)
        elif kind in POSITION_MESSAGES.values():
            track.other_types.add(kind)

    def _restart(self, track: Track, ms: int) -> None:
        self.counts["restarts"] += 1
        self.events.append(f"warning: system {track.sysid} ({track.ue_id}) restarted: its time_boot_ms went back "
                           f"from {(track.newest_ms or 0) / 1000:.3f} s to {ms / 1000:.3f} s; following its new clock")
        track.newest_ms = None
        for key in [k for k in self._seqs if k[0] == track.sysid]:
            del self._seqs[key]

    def _sequence(self, key: tuple[int, int], seq: int) -> None:
        """Gaps and reordering from the 8-bit sequence number of one sending component."""
        s = self._seqs.get(key)
        if s is None:
            self._seqs[key] = _Sequence(seq)
            return
        d = (seq - s.last) % 256
        if 0 < d < 128:  # ahead: d - 1 packets skipped
            for k in range(1, d):
                s.gaps.add((s.last + k) % 256)
            self.counts["missing"] += d - 1
            s.last = seq
            if s.gaps:  # gaps more than 127 behind can no longer be told apart: they stay missing
                s.gaps = {g for g in s.gaps if (seq - g) % 256 < 128}
        elif seq in s.gaps:  # behind, filling a gap: it came after all, late
            s.gaps.discard(seq)
            self.counts["missing"] -= 1
            self.counts["out_of_order"] += 1
        else:
            self.counts["duplicate"] += 1

    def _position(self, track: Track, m: Any, now: float) -> None:
        ms = int(m.time_boot_ms)
        if track.newest_ms is not None and ms <= track.newest_ms:
            if ms < track.newest_ms - self.late_ms:
                self.counts["late"] += 1
            return  # an older sample never replaces a newer one
        xyz = self.convert(m)
        if xyz is None:
            self.counts["no_fix"] += 1
            return
        if track.stale:
            track.stale = False
            what = "positions again" if track.sample is not None else "a first position"
            self.events.append(f"note: {track.ue_id} (system {track.sysid}): {what} after {now - track.since:.1f} s")
        track.newest_ms = ms
        v = self.velocity(m) if self.velocity is not None else None
        track.sample = Sample((float(xyz[0]), float(xyz[1]), float(xyz[2])), ms, now,
                              None if v is None else (float(v[0]), float(v[1]), float(v[2])))
        track.since = now
        track.positions += 1
        self.counts["positions"] += 1
        self.new_positions += 1

    # -- output ------------------------------------------------------------------------

    def check_stale(self, now: float) -> None:
        """A warning, once per outage, for every UE with no new position for ``stale_s``."""
        for t in self.tracks.values():
            silent = now - t.since
            if t.stale or silent <= self.stale_s:
                continue
            t.stale = True
            hint = f"; it sends {', '.join(sorted(t.other_types))}: see the 'source' parameter" if t.other_types else ""
            if t.sample is None:
                self.events.append(f"warning: no {self.wanted} from system {t.sysid} ({t.ue_id}) on {self.where} in "
                                   f"{silent:.1f} s: is the vehicle sending there, with that system ID?{hint}")
            else:
                self.events.append(f"warning: no {self.wanted} from system {t.sysid} ({t.ue_id}) for {silent:.1f} s: "
                                   f"holding its last position (its age_s grows){hint}")

    def snapshot(self, now: float) -> Snapshot:
        """The newest position of every UE that has one, the counts, and the events and
        new positions since the previous snapshot."""
        self.check_stale(now)
        positions = [(t.ue_id, t.sysid, t.sample, now - t.sample.received)
                     for t in self.tracks.values() if t.sample is not None]
        ues = [{"UE_Id": t.ue_id, "sysid": t.sysid,
                "age_s": None if t.sample is None else round(now - t.sample.received, 4),
                "stale": t.stale, "positions": t.positions} for t in self.tracks.values()]
        snap = Snapshot(positions, ues, dict(self.counts), self.new_positions, self.events)
        self.events, self.new_positions = [], 0
        return snap

    def summary(self) -> str:
        """One paragraph of counts, for the end of a run."""
        c = self.counts
        lines = [f"{c['datagrams']} datagrams on {self.where}: received {c['received']} from followed systems "
                 f"({c['positions']} positions used), late {c['late']}, out of order {c['out_of_order']}, "
                 f"missing {c['missing']}, duplicate {c['duplicate']}, garbage {c['garbage']} "
                 f"({c['garbage_bytes']} bytes), from unknown systems {c['unknown_system']}, "
                 f"of unknown message types {c['unknown_message']}, without a fix {c['no_fix']}, "
                 f"restarts {c['restarts']}"]
        for t in self.tracks.values():
            lines.append(f"  {t.ue_id} (system {t.sysid}): {t.positions} positions"
                         + (f", the last at time_boot_ms {t.sample.time_boot_ms}" if t.sample else ", none"))
        return "\n".join(lines)


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6; a ``udp:`` / ``udpin:`` prefix as in
    MAVProxy is accepted) -> (host, port)."""
    body = text.split(":", 1)[1] if text.split(":", 1)[0] in ("udp", "udpin") else text
    host, sep, port = body.rpartition(":")
    host = host.strip("[]")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"listen: expected HOST:PORT (e.g. 127.0.0.1:14550), got {text!r}")
    return host or "0.0.0.0", int(port)


class UdpReader:
    """Listens on ``host:port`` (UDP) and feeds each datagram to ``decoder`` from a
    background thread, under :attr:`lock`. :attr:`address` is where it listens (the real
    port when 0 was asked for)."""

    RECEIVE_BUFFER = 1 << 20
    """Bytes the kernel may queue while the thread is busy (SO_RCVBUF, asked for)."""

    def __init__(self, decoder: TelemetryDecoder, host: str, port: int,
                 clock: Callable[[], float] = time.monotonic):
        self.decoder, self.clock = decoder, clock
        self.lock = threading.Lock()
        info = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        self.sock = socket.socket(info[0], socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.RECEIVE_BUFFER)
            self.sock.bind(info[4])
        except OSError as e:
            self.sock.close()
            raise OSError(f"cannot listen for MAVLink on UDP {host}:{port}: {e.strerror or e} (is a ground station, "
                          "e.g. QGroundControl or MAVProxy, already listening there?)") from None
        self.sock.settimeout(0.1)  # how often the thread looks whether it should stop
        bound = self.sock.getsockname()
        self.address = f"[{bound[0]}]:{bound[1]}" if ":" in bound[0] else f"{bound[0]}:{bound[1]}"
        decoder.where = f"UDP {self.address}"
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"mavlink-{self.address}", daemon=True)

    def start(self) -> "UdpReader":
        self.thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(0.01)  # e.g. ECONNREFUSED surfaced by some kernels: keep listening
                continue
            now = self.clock()
            with self.lock:
                try:
                    self.decoder.feed(data, now)
                except Exception as e:  # a bug must not silence the vehicle for the rest of the run
                    self.decoder.events.append(f"warning: a datagram could not be handled ({type(e).__name__}: {e})")

    def snapshot(self) -> Snapshot:
        with self.lock:
            return self.decoder.snapshot(self.clock())

    def close(self) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(timeout=2.0)
        self.sock.close()
