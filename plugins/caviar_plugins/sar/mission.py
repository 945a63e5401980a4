"""The search-and-rescue mission: on a detection the UAV stops to send its images,
the rescue is counted, and the flight continues.

The stop lasts S = B / throughput with B = 10 images of 4 MB (the paper's), at the
UAV's latest throughput. A person seen again within ``same_target_m`` of a rescued
one is the same person. When the episode ends (the UAV reached its last waypoint),
``mission.result`` reports the total mission time and the rescued targets.
"""

from __future__ import annotations

import dataclasses
import math

import caviar
from caviar_plugins.schema import DETECTIONS, HOVER, RESCUE, RESULT, THROUGHPUT


class Mission(caviar.Plugin):
    subscribe = [DETECTIONS, THROUGHPUT, caviar.END_TOPIC]
    publishes = (HOVER, RESCUE, RESULT)

    @dataclasses.dataclass
    class Params:
        images: int = 10
        image_mb: float = 4.0
        """Megabytes per image (MB = 10^6 bytes)."""
        same_target_m: float = 5.0
        max_hover_s: float = 600.0
        """Upper bound of one stop, for links with (almost) no throughput."""

    def setup(self, ctx):
        self.ctx = ctx
        self.throughput: dict[str, float] = {}
        self.rescues: list[dict] = []

    def step(self, t, inbox):
        p = self.ctx.params
        for m in inbox:
            if m.topic == THROUGHPUT:
                self.throughput[m.data["UE_Id"]] = float(m.data["throughput"])
        for m in inbox.on(DETECTIONS):
            ue = m.data["UE_Id"]
            for d in m.data["detections"]:
                g = d.get("ground")
                if g is None or any(math.dist((g["x"], g["y"]), (r["x"], r["y"])) < p.same_target_m
                                    for r in self.rescues):
                    continue
                mbps = self.throughput.get(ue, 0.0)
                megabits = p.images * p.image_mb * 8
                seconds = min(megabits / mbps, p.max_hover_s) if mbps > 0 else p.max_hover_s
                rescue = {"UE_Id": ue, "x": g["x"], "y": g["y"], "time": t, "throughput": mbps,
                          "hover_s": seconds}
                self.rescues.append(rescue)
                yield HOVER, {"UE_Id": ue, "seconds": seconds}
                yield RESCUE, rescue
        end = inbox.latest(caviar.END_TOPIC)
        if end is not None:
            yield RESULT, {"mission_time_s": end.time, "rescued": len(self.rescues), "rescues": self.rescues}
