"""Image degradation by packet loss, as in the paper (Table "Image degradation").

The image is sent in packets of ``packet_bytes``; each is lost independently with a
probability set by the link's throughput (> 60 Mbit/s: 1 %, 30–60: 25 %, ≤ 30: 50 %)
and a lost packet's bytes arrive as zeros. Zero-filling reproduces the paper's PSNRs
(≈ 26, 12 and 9 dB on its images).

``protocol = "paper"`` (the 2023 loop): the loss rate follows the throughput of the
previous step, and exactly ⌊N · rate⌋ randomly chosen bytes of the image are zeroed
(:func:`caviar_plugins.protocol.zero_bytes`), from a generator seeded 1 that runs on
across frames.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.schema import CAMERA, IMAGE_QUALITY, IMAGES, THROUGHPUT, every_ue, per_ue, ue_of

# (throughput above which, loss rate), checked in order; the paper's table.
PAPER_LOSS = ((60.0, 0.01), (30.0, 0.25), (-np.inf, 0.50))


def loss_for_throughput(mbps: float, table=PAPER_LOSS) -> float:
    for above, rate in table:
        if mbps > above:
            return rate
    return table[-1][1]


def packet_loss(image: np.ndarray, rate: float, rng: np.random.Generator, packet_bytes: int = 1400) -> np.ndarray:
    flat = np.ascontiguousarray(image).reshape(-1).copy()
    n_packets = -(-flat.size // packet_bytes)
    lost = np.flatnonzero(rng.random(n_packets) < rate)
    for k in lost:
        flat[k * packet_bytes:(k + 1) * packet_bytes] = 0
    return flat.reshape(image.shape)


def psnr(original: np.ndarray, received: np.ndarray, peak: float = 255.0) -> float:
    mse = float(np.mean((original.astype(float) - received.astype(float)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(peak**2 / mse)


class ImageLink(caviar.Plugin):
    """Sends each camera image over the UAV's link: applies the packet loss of its
    latest throughput, publishes the received image on ``ai.images.<UE_Id>`` and the
    PSNR on ``ai.image_quality``."""

    subscribe = [every_ue(CAMERA), THROUGHPUT]
    publishes = (every_ue(IMAGES), IMAGE_QUALITY)

    @dataclasses.dataclass
    class Params:
        packet_bytes: int = 1400
        protocol: str = "physical"
        """``physical``: packets of ``packet_bytes``, this step's throughput; ``paper``:
        byte-level zeroing at the previous step's throughput (module docstring)."""

        def __post_init__(self):
            paper.check_protocol(self.protocol)

    def setup(self, ctx):
        self.ctx = ctx
        self.throughput: dict[str, float] = {}
        self.paper_rng = np.random.default_rng(1)

    def state(self):
        # ctx.rng (the physical packet losses) is saved by the host.
        return {"throughput": self.throughput, "paper_rng": self.paper_rng.bit_generator.state}

    def restore(self, state):
        self.throughput = state["throughput"]
        self.paper_rng.bit_generator.state = state["paper_rng"]

    def step(self, t, inbox):
        is_paper = self.ctx.params.protocol == "paper"
        previous = dict(self.throughput)
        for m in inbox:
            if m.topic == THROUGHPUT:
                self.throughput[m.data["UE_Id"]] = float(m.data["throughput"])
        for m in inbox.on(every_ue(CAMERA)):
            ue = ue_of(m.topic)
            if is_paper:
                mbps = previous.get(ue, 0.0)
                rate = loss_for_throughput(mbps, paper.PAPER_LOSS)
                received = paper.zero_bytes(m.data, rate, self.paper_rng)
            else:
                mbps = self.throughput.get(ue, 0.0)
                rate = loss_for_throughput(mbps)
                received = packet_loss(m.data, rate, self.ctx.rng, self.ctx.params.packet_bytes)
            yield per_ue(IMAGES, ue), received
            yield IMAGE_QUALITY, {"UE_Id": ue, "throughput": mbps, "loss_rate": rate,
                                        "psnr_db": min(psnr(m.data, received), 99.0), "step": m.step}
