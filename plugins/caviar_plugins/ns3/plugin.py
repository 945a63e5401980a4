"""The ``ns3-network`` plugin: the UAVs' camera images cross a real ns-3 network, in
lockstep with the engine, on the ray-traced channel.

Each engine step it

1. moves the UE nodes to the UEs' positions (``3D.mobility.positions``);
2. sets each UE's loss to the cell from the ray tracer's gain of the step
   (``communications.link``: the used beam pair's gain, or the path gain without arrays)
   in ns-3's ``MatrixPropagationLossModel``, uplink and downlink. The loss is
   frequency-flat and constant over the step;
3. queues each camera image of the step (``3D.camera.<UE_Id>``) at its UE as UDP
   packets (or into one TCP stream) to the ground station behind the network;
4. runs ns-3 to the step's end and rebuilds every image whose packets have all arrived,
   or whose ``deadline_s`` has passed, from the packets that arrived (the others' bytes
   are zeros, as the paper's loop did), and publishes it on ``ai.images.<UE_Id>`` for the
   detector, with what its delivery took on ``ai.image_quality``.

The packets carry the image's real size and an 8-byte (image, packet) header; the
receiver takes each arrived packet's bytes from the image sent. That is the same as
carrying the pixels, since ns-3 delivers a packet whole or not at all. The header is the
plugin's, not the application's: ``network.ns3.link`` counts image bytes only.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np

import caviar
from caviar_plugins.ns3 import simulator as sim
from caviar_plugins.schema import (
    CAMERA,
    IMAGE_QUALITY,
    IMAGES,
    LINK,
    NS3_LINK,
    POSITIONS,
    every_ue,
    per_ue,
    read_position,
    ue_of,
)
from caviar_plugins.vision.image_link import psnr

# ns-3 loads with the plugin class, not in setup: cppyy parses its headers for seconds
# holding the interpreter lock, which would silence a NATS worker's heartbeat; while the
# plugin loads, the core waits up to transport.nats.startup_timeout instead.
sim.load()


@dataclasses.dataclass
class PendingImage:
    ue: str
    image: int
    step: int
    sent_at: float
    data: np.ndarray
    packets: int
    """UDP packets sent (TCP: 0)."""
    stream_end: int = 0
    """TCP: the stream offset just past this image's bytes."""
    arrived: set[int] = dataclasses.field(default_factory=set)
    received_bytes: int = 0
    last_arrival: float | None = None


class Ns3Network(caviar.Plugin):
    """The UAVs' images over ns-3 (LTE with its EPC, or point-to-point links)."""

    subscribe = [POSITIONS, LINK, every_ue(CAMERA)]
    optional = (LINK,)
    publishes = (every_ue(IMAGES), IMAGE_QUALITY, NS3_LINK)

    @dataclasses.dataclass
    class Params:
        ues: list[str] = dataclasses.field(default_factory=lambda: ["uav1"])
        """The UEs ns-3 has a node for (an image from another UE is an error)."""
        ran: str = "lte"
        """``lte``: LTE with its EPC (one eNB, PGW, a point-to-point backhaul to the ground
        station); ``p2p``: one point-to-point link per UE (no radio; delay = propagation +
        serialisation + queueing)."""
        transport: str = "udp"
        """``udp``: packets of ``payload_bytes``, a lost packet's bytes arrive as zeros;
        ``tcp``: one stream per UE, the image is what arrived of it by the deadline."""
        payload_bytes: int = 1400
        """Image bytes per UDP packet (each packet adds 8 bytes of header, then UDP/IP)."""
        deadline_s: float = 0.0
        """How long after sending an image the receiver waits for it; 0: one step (the
        image reaches the detector in the step it was taken)."""
        loss_from: str = "pair"
        """``pair``: the used beam pair's gain (path gain with both arrays' beamforming;
        ns-3's antennas are isotropic); ``path``: the path gain alone."""
        enb_position: list[float] = dataclasses.field(default_factory=lambda: [-154.0, 64.0, 120.0])
        """Where the eNB stands (the ray tracer's transmitter)."""
        lte: sim.LteSettings = dataclasses.field(default_factory=sim.LteSettings)
        """``ran = "lte"``: ``bandwidth_rb``, ``scheduler``, the backhaul, ``rlc_buffer_bytes``
        (see :class:`~caviar_plugins.ns3.simulator.LteSettings`)."""
        p2p: sim.P2pSettings = dataclasses.field(default_factory=sim.P2pSettings)
        """``ran = "p2p"``: ``rate``, ``delay_s``, ``queue`` (see
        :class:`~caviar_plugins.ns3.simulator.P2pSettings`)."""
        attributes: dict[str, Any] = dataclasses.field(default_factory=dict)
        """ns-3 attribute defaults, set before the network is built:
        ``{"ns3::LteUePhy::TxPower" = 23, "ns3::LteEnbPhy::NoiseFigure" = 5}``."""

        def __post_init__(self):
            if not self.ues or len(set(self.ues)) != len(self.ues):
                raise ValueError(f"ues: expected distinct UE ids, got {self.ues}")
            if self.ran not in sim.RAN_KINDS:
                why = sim.NOT_IN_WHEEL.get(self.ran.lower())
                raise ValueError(f"ran: expected one of {', '.join(sim.RAN_KINDS)}, got {self.ran!r}"
                                 + (f" ({why})" if why else ""))
            if self.transport not in ("udp", "tcp"):
                raise ValueError(f"transport: expected 'udp' or 'tcp', got {self.transport!r}")
            if self.loss_from not in ("pair", "path"):
                raise ValueError(f"loss_from: expected 'pair' or 'path', got {self.loss_from!r}")
            if not 64 <= self.payload_bytes <= 65000:
                raise ValueError(f"payload_bytes: expected 64..65000, got {self.payload_bytes}")
            if not (math.isfinite(self.deadline_s) and self.deadline_s >= 0):
                raise ValueError(f"deadline_s: expected >= 0 s (0: one step), got {self.deadline_s}")
            if len(self.enb_position) != 3 or not all(math.isfinite(v) for v in self.enb_position):
                raise ValueError(f"enb_position: expected [x, y, z] in metres, got {self.enb_position}")

    @classmethod
    def check_params(cls, params, config_dir):
        # ns-3 itself says whether each setting and attribute is one it takes (ns-3 loaded
        # with the plugin; a value is parsed in a child process, which alone aborts if ns-3 does).
        sim.check_settings(params.lte, params.p2p)
        if params.attributes:
            sim.check_attributes(params.attributes)
            sim.load().caviar_ns3.Reset()

    def setup(self, ctx):
        self.ctx = ctx
        p = self.p = ctx.params
        self.dt = ctx.ts * ctx.every
        self.deadline = p.deadline_s or self.dt
        self.index = {ue: i for i, ue in enumerate(p.ues)}
        self.net = sim.Ns3Simulation(
            len(p.ues), p.ran, tcp=p.transport == "tcp", seed=ctx.seed,
            lte=p.lte, p2p=p.p2p,
            attributes=p.attributes)
        self.net.set_enb_position(p.enb_position)
        self.pending: dict[int, PendingImage] = {}
        self.next_image = 0
        self.stream_sent = [0] * len(p.ues)
        self.stream_received = [0] * len(p.ues)
        self.loss_db: dict[str, float] = {}
        self.warned: set[int] = set()

    def teardown(self):
        if getattr(self, "net", None) is not None:
            self.net.close()

    def state(self):
        # ns-3's own state cannot be saved: the journal of what the plugin did to it can,
        # and replaying it on a new network gives the same state (restore).
        return {"journal": list(self.net.journal), "pending": self.pending, "next_image": self.next_image,
                "stream_sent": self.stream_sent, "stream_received": self.stream_received,
                "loss_db": self.loss_db}

    def restore(self, state):
        self.net.replay(state["journal"])
        self.pending = state["pending"]
        self.next_image = state["next_image"]
        self.stream_sent = state["stream_sent"]
        self.stream_received = state["stream_received"]
        self.loss_db = state["loss_db"]

    def _node(self, ue: str, topic: str) -> int:
        i = self.index.get(ue)
        if i is None:
            raise ValueError(f"modules.{self.ctx.name}.params.ues: ns-3 has no node for UE {ue!r} "
                             f"(it sent {topic}); the nodes are {self.p.ues}")
        return i

    def step(self, t, inbox):
        self._channel(inbox)
        self._send(inbox)
        end = t + self.dt
        self.net.run_until(end)
        delivered = self._receive()
        for image in sorted(self.pending):
            img = self.pending[image]
            complete = img.received_bytes == img.data.nbytes
            if complete or end >= img.sent_at + self.deadline - 1e-9:
                del self.pending[image]
                yield from self._release(img, complete, end)
        p = self.p
        for ue, up in zip(p.ues, self.net.uplink(), strict=True):
            i = self.index[ue]
            yield NS3_LINK, {
                "UE_Id": ue, "time": t, "ran": p.ran, "loss_db": self.loss_db.get(ue),
                "delivered_bytes": delivered[i], "throughput_mbps": delivered[i] * 8 / self.dt / 1e6,
                "sinr_db": None if up is None else up.sinr_db, "mcs": None if up is None else up.mcs,
                "grants": None if up is None else up.grants, "tb_bytes": None if up is None else up.tb_bytes,
            }

    def _channel(self, inbox) -> None:
        """The step's positions and losses into ns-3."""
        for m in inbox.on(POSITIONS):
            i = self.index.get(m.data["UE_Id"])
            if i is not None:
                self.net.set_position(i, [float(v) for v in read_position(m.data)])
        for m in inbox.on(LINK):
            ue = m.data["UE_Id"]
            if ue in self.index:
                gain_db = m.data.get("pair_gain_db") if self.p.loss_from == "pair" else None
                if gain_db is None:
                    gain_db = m.data["path_gain_db"]
                loss = -float(gain_db)
                self.loss_db[ue] = loss if math.isfinite(loss) else 400.0  # no path at all
                self.net.set_loss(self.index[ue], self.loss_db[ue])

    def _send(self, inbox) -> None:
        """The step's camera images, queued at their UEs now."""
        p = self.p
        now = self.net.now()
        for m in inbox.on(every_ue(CAMERA)):
            if m.topic.count(".") != 2:  # .file / .depth
                continue
            ue = ue_of(m.topic)
            i = self._node(ue, m.topic)
            data = np.ascontiguousarray(m.data)
            image = self.next_image
            self.next_image += 1
            self._check_fits(ue, data.nbytes)
            sent = self.net.send(i, image, data.nbytes, p.payload_bytes)
            if p.transport == "tcp":
                if sent != data.nbytes:
                    raise RuntimeError(f"TCP send buffer full at UE {ue!r}: {sent} of {data.nbytes} bytes queued")
                self.stream_sent[i] += data.nbytes
            self.pending[image] = PendingImage(ue, image, self.ctx.step, now, data,
                                               sent if p.transport == "udp" else 0, stream_end=self.stream_sent[i])

    def _check_fits(self, ue: str, nbytes: int) -> None:
        """Warns (once per size) when a fixed RLC buffer cannot hold one image: its tail is
        dropped at the UE, whatever the channel."""
        p = self.p
        fixed = p.lte.rlc_buffer_bytes if p.ran == "lte" else 0
        need = sim.rlc_sdu_bytes(nbytes, p.payload_bytes, p.transport == "tcp")
        if fixed and need > fixed and need not in self.warned:
            self.warned.add(need)
            warnings.warn(f"modules.{self.ctx.name}.params.lte.rlc_buffer_bytes = {fixed} cannot hold one image "
                          f"of UE {ue!r} ({nbytes} bytes, {need} with its packets' headers): what does not fit is "
                          "dropped at the UE's RLC on every image; raise it, or 0 to size it from the load",
                          stacklevel=2)

    def _receive(self) -> list[int]:
        """What reached the ground station in the step, onto the pending images; image bytes
        per UE (UDP: less the plugin's 8-byte header of each packet)."""
        payload = self.p.payload_bytes
        header = 0 if self.p.transport == "tcp" else sim.HEADER_BYTES
        delivered = [0] * len(self.p.ues)
        for a in self.net.arrivals():
            delivered[a.ue] += a.bytes - header
            if self.p.transport == "tcp":
                self._stream_arrival(a)
                continue
            img = self.pending.get(a.image)
            if img is not None and a.index not in img.arrived:
                img.arrived.add(a.index)
                img.received_bytes += min(payload, img.data.nbytes - a.index * payload)
                img.last_arrival = a.time_s
        return delivered

    def _stream_arrival(self, a: sim.Arrival) -> None:
        """TCP: stream bytes [received, received + a.bytes) belong to the images in order."""
        start = self.stream_received[a.ue]
        self.stream_received[a.ue] = stop = start + a.bytes
        for img in self.pending.values():
            if self.index[img.ue] != a.ue:
                continue
            lo = img.stream_end - img.data.nbytes
            got = max(0, min(stop, img.stream_end) - max(start, lo))
            if got:
                img.received_bytes += got
                img.last_arrival = a.time_s

    def _release(self, img: PendingImage, complete: bool, end: float):
        p = self.p
        data = img.data
        flat = data.reshape(-1)
        received = np.zeros_like(flat)
        if p.transport == "udp":
            size = p.payload_bytes
            for k in img.arrived:
                received[k * size:(k + 1) * size] = flat[k * size:(k + 1) * size]
            lost = img.packets - len(img.arrived)
        else:
            received[:img.received_bytes] = flat[:img.received_bytes]  # the stream's prefix
            lost = 0
        received = received.reshape(data.shape)
        delay = (img.last_arrival - img.sent_at) if complete and img.last_arrival is not None else None
        yield per_ue(IMAGES, img.ue), received
        yield IMAGE_QUALITY, {
            "UE_Id": img.ue, "step": img.step, "image": img.image, "network": "ns-3 " + p.ran,
            "sent_at": img.sent_at, "released_at": end, "complete": complete, "delay_s": delay,
            "bytes_sent": int(data.nbytes), "bytes_received": int(img.received_bytes),
            "packets_sent": img.packets, "packets_lost": lost,
            "loss_rate": 1.0 - img.received_bytes / data.nbytes,
            "throughput": (img.received_bytes * 8 / max(img.last_arrival - img.sent_at, 1e-9) / 1e6
                           if img.last_arrival is not None else 0.0),
            "psnr_db": min(psnr(data, received), 99.0),
        }
