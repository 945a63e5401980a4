"""ns-3 in lockstep: one network of UEs and a ground station, advanced one engine step
at a time (:class:`Ns3Simulation`).

The real ns-3 (PyPI's ``ns3`` wheel, cppyy bindings) runs the packets; the small C++
half (``caviar_ns3.h``, compiled by cppyy on first use) owns the sockets and the trace
sinks, so ns-3 never calls into Python. After each ``Simulator::Run()`` Python reads the
arrivals and the uplink statistics of the step.

ns-3's simulator is a process-wide singleton: one :class:`Ns3Simulation` lives at a
time; :meth:`Ns3Simulation.close` destroys it and resets ns-3's defaults and address
pools so that the next one starts clean.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Callable, Mapping, Sequence, TypeVar

from caviar_plugins.ns3.checks import check_attributes, check_seconds, check_settings
from caviar_plugins.ns3.native import HEADERS, Ns3Aborted, Ns3Unavailable, guarded, load

__all__ = ["HEADERS", "Ns3Aborted", "Ns3Unavailable", "check_attributes", "load"]

RAN_KINDS = ("lte", "p2p")
"""Networks this plugin builds from the ``ns3`` wheel: ``lte`` (LTE with its EPC: the
UEs, one eNB, a point-to-point backhaul to the ground station) and ``p2p`` (one
point-to-point link per UE, no radio: the reference case)."""

NOT_IN_WHEEL = {
    "nr": "5G-LENA (ns-3's NR module) is not built into PyPI's ns3 3.44 wheel",
    "5g": "5G-LENA (ns-3's NR module) is not built into PyPI's ns3 3.44 wheel",
    "5g-lena": "5G-LENA is not built into PyPI's ns3 3.44 wheel",
    "mmwave": "ns-3's mmwave module is not built into PyPI's ns3 3.44 wheel",
    "wifi": "the wifi module is in the wheel, but this plugin builds LTE and point-to-point only",
}

BASE_PORT = 9000
UDP_IP_BYTES = 8 + 20
"""UDP and IPv4 headers on every packet (ns-3 adds no options)."""
HEADER_BYTES = 8
"""The plugin's own header on each UDP packet: image id and packet index (u32 each)."""
PPP_BYTES = 2
"""The point-to-point header ns-3's PointToPointNetDevice adds."""
PDCP_BYTES = 2
"""The PDCP header on each packet into the RLC (12-bit sequence numbers)."""
TCP_IP_BYTES = 20 + 20
TCP_SEGMENT_BYTES = 536
"""ns-3's default TCP segment (``ns3::TcpSocket::SegmentSize``)."""
RLC_BUFFER_MIN = 128 * 1024
"""The UE's RLC buffer when it is sized from the load, at least (bytes)."""


def rlc_sdu_bytes(nbytes: int, payload_bytes: int, tcp: bool) -> int:
    """What ``nbytes`` of image take in a UE's RLC buffer: the packets with their headers
    (UDP: the plugin's 8 bytes, UDP/IP and PDCP; TCP: segments of ns-3's default size with
    TCP/IP and PDCP)."""
    if tcp:
        return nbytes + math.ceil(nbytes / TCP_SEGMENT_BYTES) * (TCP_IP_BYTES + PDCP_BYTES)
    return nbytes + math.ceil(nbytes / payload_bytes) * (HEADER_BYTES + UDP_IP_BYTES + PDCP_BYTES)


@dataclasses.dataclass
class Arrival:
    """One packet (UDP) or chunk of stream (TCP) at the ground station."""

    ue: int
    image: int
    index: int
    bytes: int
    time_s: float


@dataclasses.dataclass
class UplinkStep:
    """What the eNB saw of one UE over a step (LTE only)."""

    sinr_db: float | None
    """Mean of the SRS SINRs the eNB reported (ns-3's ``ReportUeSinr``)."""
    mcs: float | None
    """Mean MCS of the uplink grants (``UlScheduling``)."""
    mcs_mode: int | None
    """The MCS granted most often."""
    grants: int
    tb_bytes: float
    """Transport-block bytes granted."""


@dataclasses.dataclass(frozen=True)
class LteSettings:
    """``[modules.NAME.params.lte]``: the LTE network (``ran = "lte"``)."""

    bandwidth_rb: int = 25
    """Uplink and downlink bandwidth in resource blocks (6, 15, 25, 50, 75 or 100)."""
    scheduler: str = "ns3::PfFfMacScheduler"
    backhaul_rate: str = "10Gbps"
    """The point-to-point link from the PGW to the ground station."""
    backhaul_delay_s: float = 0.001
    attach_loss_db: float = 100.0
    """The UE–eNB loss while the UEs attach (before the first loss is set)."""
    rlc_buffer_bytes: int = 0
    """The UE's RLC transmit buffer (RLC UM), bytes; a packet that finds it full is dropped.
    0 (the default): sized from the load, to hold twice the images a UE is given in one
    step, with their headers (at least :data:`RLC_BUFFER_MIN`): a step's images always fit,
    and after an outage new images do not queue behind many stale ones. ns-3's own default, 10 kB, would drop most
    of every image. Set, it is fixed; an image that cannot fit in it is warned about."""

    def __post_init__(self):
        if self.bandwidth_rb not in (6, 15, 25, 50, 75, 100):
            raise ValueError(f"bandwidth_rb: expected 6, 15, 25, 50, 75 or 100, got {self.bandwidth_rb}")
        if self.rlc_buffer_bytes != 0 and not 10240 <= self.rlc_buffer_bytes < 2**32:
            raise ValueError(f"rlc_buffer_bytes: expected 0 (sized from the load) or 10240 .. 2**32 - 1, "
                             f"got {self.rlc_buffer_bytes}")
        check_seconds("backhaul_delay_s", self.backhaul_delay_s)
        if not math.isfinite(self.attach_loss_db):
            raise ValueError(f"attach_loss_db: expected a loss in dB, got {self.attach_loss_db}")


@dataclasses.dataclass(frozen=True)
class P2pSettings:
    """``[modules.NAME.params.p2p]``: one point-to-point link per UE (``ran = "p2p"``)."""

    rate: str = "20Mbps"
    delay_s: float = 0.005
    queue: str = "100000p"
    """The device's DropTail queue, in packets (``"100p"``) or bytes (``"64KB"``)."""

    def __post_init__(self):
        check_seconds("delay_s", self.delay_s)


F = TypeVar("F", bound=Callable[..., Any])

DOING = {"__init__": "while building the network", "run_until": "while running", "send": "while queuing an image",
         "set_position": "while moving a node", "set_enb_position": "while moving the eNB",
         "set_loss": "while setting a loss", "replay": "while replaying the journal",
         "arrivals": "while reading arrivals", "uplink": "while reading the uplink's statistics",
         "close": "while closing the network"}
"""What a guarded method was doing, for the message of an abort inside it."""


def _native(method: F) -> F:
    """The method's calls into ns-3 cannot end the process: an abort inside raises
    :class:`Ns3Aborted` naming what was being done, and the network is marked dead."""

    @functools.wraps(method)
    def call(self, *args, **kwargs):
        if getattr(self, "aborted", None):
            raise Ns3Aborted(f"ns-3 aborted earlier ({self.aborted}); this network cannot go on")

        def dead(words: str) -> None:
            self.aborted = words

        with guarded(DOING.get(method.__name__, "in " + method.__name__), dead):
            return method(self, *args, **kwargs)

    return call  # type: ignore[return-value]


class Ns3Simulation:
    """One ns-3 network, advanced by :meth:`run_until`.

    ``ues``: how many UE nodes (index 0..n-1); ``ran``: one of :data:`RAN_KINDS`;
    ``tcp``: one TCP stream per UE instead of UDP packets; ``warmup_s``: ns-3 time run
    before the engine's time 0 (the UEs attach; with TCP 50 ms more for the handshakes;
    ns-3 time = engine time + that).
    """

    aborted: str | None = None
    """ns-3's words if it aborted inside a call: the network cannot go on."""

    @_native
    def __init__(self, ues: int, ran: str = "lte", *, tcp: bool = False, seed: int = 1,
                 lte: LteSettings | None = None, p2p: P2pSettings | None = None,
                 attributes: Mapping[str, Any] | None = None, warmup_s: float = 0.1):
        if ran not in RAN_KINDS:
            raise ValueError(f"ran: expected one of {', '.join(RAN_KINDS)}, got {ran!r}"
                             + (f" ({NOT_IN_WHEEL[ran.lower()]})" if ran.lower() in NOT_IN_WHEEL else ""))
        check_settings(lte or LteSettings(), p2p or P2pSettings())
        g = load()
        self.g, self.ns = g, g.ns3
        self.c = g.caviar_ns3
        self.c.Reset()  # a previous network in this process leaves nothing behind
        self.ran, self.tcp, self.n = ran, tcp, ues
        self.ns.RngSeedManager.SetSeed(1)
        self.ns.RngSeedManager.SetRun(max(1, int(seed)))
        if tcp:
            # Images go whole into the stream: a send buffer that holds many of them.
            self.c.SetDefault("ns3::TcpSocket::SndBufSize", str(64 << 20))
            self.c.SetDefault("ns3::TcpSocket::RcvBufSize", str(64 << 20))
        if ran == "lte":
            self.lte = lte or LteSettings()
            # Queue a step's images rather than drop most of one at the RLC (ns-3's default
            # buffer: 10 kB; see LteSettings.rlc_buffer_bytes); stay attached out of coverage
            # (images are lost, the UE does not re-attach). ns-3's PDCP discard timer acts
            # only as a packet enters the RLC.
            self.c.SetDefault("ns3::LteEnbRrc::EpsBearerToRlcMapping", "RlcUmAlways")
            self.rlc_buffer = [self.lte.rlc_buffer_bytes or RLC_BUFFER_MIN] * ues
            """Each UE's RLC transmit buffer now (bytes)."""
            self._queued = [0] * ues
            """RLC bytes each UE was given since the last run_until."""
            self.c.SetDefault("ns3::LteRlcUm::MaxTxBufferSize", str(self.rlc_buffer[0]))
            self.c.SetDefault("ns3::LteUePhy::EnableRlfDetection", "false")
        check_attributes(attributes or {})
        self.wall_s = 0.0
        t0 = time.perf_counter()
        if ran == "lte":
            s = self.lte
            self.net = self.c.BuildLte(ues, s.bandwidth_rb, s.scheduler, s.backhaul_rate,
                                       s.backhaul_delay_s, s.attach_loss_db)
        else:
            s2 = p2p or P2pSettings()
            self.net = self.c.BuildP2p(ues, s2.rate, s2.delay_s, s2.queue)
        # Run once even for no warm-up: the nodes initialize (their traffic control layer
        # finds its devices) in the simulator's first events. Then the UEs attach, and only
        # then do the flows open: a TCP handshake before the attach would wait out its
        # retransmission timeouts (seconds).
        self.ns.Simulator.Stop(self.ns.Seconds(0))
        self.ns.Simulator.Run()
        self._run_to(warmup_s)
        self.net.AddFlows(tcp, BASE_PORT)
        if tcp:
            warmup_s += 0.05  # the handshake
            self._run_to(warmup_s)
        self.warmup_s = warmup_s
        self.wall_s += time.perf_counter() - t0
        self.journal: list[tuple] = []
        """Every call that changed the network since it was built, in order: replayed on a
        new network (:meth:`replay`) it brings ns-3 to the same state, event for event."""
        self.rntis = [int(self.net.Rnti(i)) for i in range(ues)] if ran == "lte" else []

    # -- per step ----------------------------------------------------------------------
    @_native
    def set_position(self, ue: int, xyz: Sequence[float]) -> None:
        x, y, z = (float(v) for v in xyz)
        self.journal.append(("position", ue, x, y, z))
        self.net.SetPosition(ue, x, y, z)

    @_native
    def set_enb_position(self, xyz: Sequence[float]) -> None:
        if self.ran == "lte":
            x, y, z = (float(v) for v in xyz)
            self.journal.append(("enb", x, y, z))
            self.net.SetEnbPosition(x, y, z)

    @_native
    def set_loss(self, ue: int, loss_db: float) -> None:
        """The UE–cell loss in dB (both directions), until set again (LTE only)."""
        if self.ran == "lte":
            self.journal.append(("loss", ue, float(loss_db)))
            self.net.SetLoss(ue, float(loss_db))

    @_native
    def send(self, ue: int, image: int, nbytes: int, payload_bytes: int) -> int:
        """Queues ``nbytes`` of image ``image`` at UE ``ue`` now. UDP: returns the packets
        (``payload_bytes`` of image each, plus the 8-byte header); TCP: the bytes queued.
        LTE with the RLC buffer sized from the load: the UE's grows first to hold twice what
        it was given since the last :meth:`run_until`."""
        self.journal.append(("send", ue, image, nbytes, payload_bytes))
        if self.ran == "lte" and not self.lte.rlc_buffer_bytes:
            self._queued[ue] += rlc_sdu_bytes(nbytes, payload_bytes, self.tcp)
            need = min(2 * self._queued[ue], 2**32 - 1)
            if need > self.rlc_buffer[ue]:
                self.rlc_buffer[ue] = need
                self.net.SetRlcBuffer(ue, need)
                self.c.SetDefault("ns3::LteRlcUm::MaxTxBufferSize", str(max(self.rlc_buffer)))  # bearers to come
        return int(self.net.senders[ue].Send(image, nbytes, payload_bytes))

    @_native
    def replay(self, journal: Sequence[tuple]) -> None:
        """Brings this new network to where another one was after ``journal`` (its
        :attr:`journal`): ns-3 is deterministic, so the same calls give the same events.
        What arrived meanwhile is dropped (the caller kept its own account)."""
        for op, *args in journal:
            if op == "position":
                self.set_position(args[0], args[1:])
            elif op == "enb":
                self.set_enb_position(args)
            elif op == "loss":
                self.set_loss(*args)
            elif op == "send":
                self.send(*args)
            elif op == "run":
                self.run_until(args[0])
            else:
                raise ValueError(f"unknown journal entry {op!r}")
        self.arrivals()
        self.uplink()

    def now(self) -> float:
        """Engine time of ns-3's clock."""
        return round(float(self.ns.Simulator.Now().GetSeconds()) - self.warmup_s, 9)  # ns-3 counts ns

    @_native
    def run_until(self, t_engine: float) -> None:
        self.journal.append(("run", t_engine))
        if self.ran == "lte":
            self._queued = [0] * self.n
        t0 = time.perf_counter()
        self._run_to(t_engine + self.warmup_s)
        self.wall_s += time.perf_counter() - t0

    def _run_to(self, t_ns3: float) -> None:
        dt = t_ns3 - float(self.ns.Simulator.Now().GetSeconds())
        if dt > 0:
            self.ns.Simulator.Stop(self.ns.Seconds(dt))
            self.ns.Simulator.Run()

    @_native
    def arrivals(self) -> list[Arrival]:
        """The packets that reached the ground station since the last call (engine times)."""
        out = []
        for ue, r in enumerate(self.net.receivers):
            n = r.time_.size()
            if n:
                images, index, nbytes, times = list(r.image_), list(r.index_), list(r.bytes_), list(r.time_)
                out += [Arrival(ue, int(images[k]), int(index[k]), int(nbytes[k]),
                                round(float(times[k]) - self.warmup_s, 9)) for k in range(n)]
                r.Clear()
        return out

    @_native
    def uplink(self) -> list[UplinkStep | None]:
        """Per UE, the eNB's view of its uplink since the last call (None for ``p2p``)."""
        if self.ran != "lte":
            return [None] * self.n
        st = self.net.stats
        out: list[UplinkStep | None] = []
        for rnti in self.rntis:
            sinr, grants = float(st.MeanSinr(rnti)), int(st.Grants(rnti))
            out.append(UplinkStep(
                sinr_db=10 * math.log10(sinr) if sinr > 0 else None,
                mcs=float(st.MeanMcs(rnti)) if grants else None,
                mcs_mode=int(st.ModeMcs(rnti)) if grants else None,
                grants=grants, tb_bytes=float(st.TbBytes(rnti))))
        st.Clear()
        return out

    def close(self) -> None:
        """Destroys the network and resets ns-3 for the next one (after an abort, ns-3's
        state is undefined: the network is dropped as it is)."""
        if getattr(self, "net", None) is not None:
            net, self.net = self.net, None
            if not self.aborted:
                with guarded(DOING["close"]):
                    self.c.Reset()
            del net
