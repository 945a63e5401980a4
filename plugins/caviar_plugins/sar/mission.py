"""The search-and-rescue mission: on a detection the UAV stops to send its images,
the rescue is counted, and the flight continues.

The stop lasts S = B / throughput with B = 10 images of 4 MB (the paper's), at the
UAV's latest throughput. With ``upload = "network"`` the B bytes go to the network instead
(``mission.upload``, carried uplink by ``radio-network``'s ``traffic.carry``), and the UAV
hovers, a step at a time, until ``network.transfers`` says they were delivered: the stop is
what the uplink took, queueing behind the camera's images included. ``mission.rescue`` is
then published when the upload completes, with its delay as ``hover_s`` and its
user-perceived throughput as ``throughput`` (``uploaded: false`` at the end for one still
under way).

With ``uav-energy`` in the loop (``uav.energy``), a UAV whose battery would not last the
way home (``must_return``) is sent home (``mission.return``, at the speed the energy
model chose); on its way it stops for no one. ``mission.result`` then reports each UAV's
energy and the energy per rescue. A person seen again within ``same_target_m`` of a rescued
one is the same person. When the episode ends (the UAV reached its last waypoint),
``mission.result`` reports the total mission time and the rescued targets.

``protocol = "paper"`` (the 2023 loop, docs/paper-protocol.md): S uses the throughput
of the previous step (the 2023 loop's lag); a detection while that throughput is 0
counts nothing (the 2023 ZeroDivisionError); a frame counts at most one rescue (the
2023 loop counted one event per frame); S is not capped; the hover itself is
served by the flight at the next waypoint (``waypoint-flight`` with the same
protocol), and the mission time is the flight's clock, takeoff included.
"""

from __future__ import annotations

import dataclasses
import math

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.schema import (
    DETECTIONS,
    ENERGY,
    HOVER,
    NETWORK_TRANSFERS,
    RESCUE,
    RESULT,
    RETURN_HOME,
    THROUGHPUT,
    UPLOAD,
)

UPLOADS = ("throughput", "network")


class Mission(caviar.Plugin):
    subscribe = [DETECTIONS, THROUGHPUT, ENERGY, caviar.END_TOPIC]
    optional = (ENERGY,)  # (a battery model, when there is one)
    publishes = (HOVER, RESCUE, RESULT, RETURN_HOME)

    @classmethod
    def inputs(cls, params):
        return {NETWORK_TRANSFERS: "params.upload"} if params.upload == "network" else {}

    @classmethod
    def outputs(cls, params):
        return (UPLOAD,) if params.upload == "network" else ()

    @dataclasses.dataclass
    class Params:
        images: int = 10
        image_mb: float = 4.0
        """Megabytes per image (MB = 10^6 bytes)."""
        same_target_m: float = 5.0
        max_hover_s: float = 600.0
        """Upper bound of one stop, for links with (almost) no throughput (physical only)."""
        protocol: str = "physical"
        """``physical`` or ``paper`` (see the module docstring)."""
        upload: str = "throughput"
        """``throughput``: hover S = B / throughput (the paper's); ``network``: hover until the
        network has delivered the B bytes (see the module docstring)."""

        def __post_init__(self):
            paper.check_protocol(self.protocol)
            if self.upload not in UPLOADS:
                raise ValueError(f"upload: expected one of {list(UPLOADS)}, got {self.upload!r}")
            if self.upload == "network" and self.protocol == "paper":
                raise ValueError("upload: the paper's protocol times the stop from the throughput; "
                                 "upload = \"network\" needs protocol = \"physical\"")

    def setup(self, ctx):
        self.ctx = ctx
        self.throughput: dict[str, float] = {}
        self.rescues: list[dict] = []
        self.energy: dict[str, dict] = {}  # UE_Id -> its latest uav.energy
        self.returning: list[str] = []
        self.uploading: dict[str, list[dict]] = {}  # UE_Id -> its rescues whose images are on the way

    def state(self):
        return {"throughput": self.throughput, "rescues": self.rescues, "energy": self.energy,
                "returning": self.returning, "uploading": self.uploading}

    def restore(self, state):
        self.throughput, self.rescues = state["throughput"], state["rescues"]
        self.energy, self.returning = state.get("energy", {}), state.get("returning", [])  # (older checkpoints)
        self.uploading = state.get("uploading", {})

    def step(self, t, inbox):
        p = self.ctx.params
        is_paper = p.protocol == "paper"
        previous = dict(self.throughput)
        for m in inbox:
            if m.topic == THROUGHPUT:
                self.throughput[m.data["UE_Id"]] = float(m.data["throughput"])
        yield from self._send_home(inbox, is_paper)
        networked = p.upload == "network"
        if networked:
            yield from self._uploaded(inbox)
        end = inbox.latest(caviar.END_TOPIC)
        detections = [] if (is_paper and end is not None) else inbox.on(DETECTIONS)
        for m in detections:
            ue = m.data["UE_Id"]
            if ue in self.returning:
                continue  # (on its way home it stops for no one)
            for d in m.data["detections"]:
                g = d.get("ground")
                if g is None or any(math.dist((g["x"], g["y"]), (r["x"], r["y"])) < p.same_target_m
                                    for r in self.rescues):
                    continue
                if networked:
                    yield from self._upload(ue, g, t)
                    continue
                stop = self._stop(ue, previous if is_paper else self.throughput)
                if stop is None:
                    continue
                mbps, seconds = stop
                rescue = {"UE_Id": ue, "x": g["x"], "y": g["y"], "time": t, "throughput": mbps,
                          "hover_s": seconds}
                self.rescues.append(rescue)
                yield HOVER, {"UE_Id": ue, "seconds": seconds}
                yield RESCUE, rescue
                if is_paper:
                    break  # 2023: one detection event per frame, whatever the number of boxes
        yield from self._hold(end)
        if end is not None:
            yield RESULT, self._result(end, is_paper)

    def _upload(self, ue: str, ground: dict, t: float):
        """A rescue whose images go to the network: ``mission.upload``, and the UAV waits."""
        p = self.ctx.params
        rescue = {"UE_Id": ue, "x": ground["x"], "y": ground["y"], "time": t}
        self.rescues.append(rescue)
        self.uploading.setdefault(ue, []).append(rescue)
        yield UPLOAD, {"UE_Id": ue, "bytes": int(p.images * p.image_mb * 1e6), "rescue": len(self.rescues) - 1}

    def _hold(self, end):
        """Holds each UAV one more step while an upload of its lasts; at the end, the rescues
        whose uploads were still under way."""
        for ue, pending in self.uploading.items():
            if pending and end is None:
                yield HOVER, {"UE_Id": ue, "seconds": self.ctx.ts * self.ctx.every}
            if end is not None:
                for rescue in pending:
                    rescue.update(throughput=None, hover_s=round(end.time - rescue["time"], 6), uploaded=False)
                    yield RESCUE, rescue

    def _uploaded(self, inbox):
        """The rescues whose images the network delivered (each UE's uploads in order)."""
        for m in inbox.on(NETWORK_TRANSFERS):
            x = m.data
            pending = self.uploading.get(x["UE_Id"])
            if x.get("source") != UPLOAD or not pending:
                continue
            rescue = pending.pop(0)
            if x.get("lost"):
                rescue.update(throughput=None, hover_s=None, uploaded=False)
            else:
                rescue.update(throughput=x["upt_mbps"], hover_s=round(x["delivered_s"] - rescue["time"], 6),
                              uploaded=True)
            yield RESCUE, rescue

    def _send_home(self, inbox, is_paper: bool):
        """``mission.return`` for a UAV whose battery would not last the way home."""
        for m in inbox.on(ENERGY):
            e = self.energy[m.data["UE_Id"]] = m.data
            if e["must_return"] and e["UE_Id"] not in self.returning and not is_paper:
                self.returning.append(e["UE_Id"])
                yield RETURN_HOME, {"UE_Id": e["UE_Id"], "speed_mps": e["return_speed_mps"], "home": e["home"],
                                    "reason": f"battery: {e['remaining_wh']:.2f} Wh left, {e['return_wh']:.2f} Wh "
                                              f"to fly home and {e['reserve_wh']:.2f} Wh of reserve"}

    def _stop(self, ue: str, throughput: dict[str, float]) -> tuple[float, float] | None:
        """(throughput, hover seconds) of a rescue, or None when it does not count."""
        p = self.ctx.params
        mbps = throughput.get(ue, 0.0)
        megabits = p.images * p.image_mb * 8
        if p.protocol == "paper":
            return None if mbps <= 0 else (mbps, megabits / mbps)
        return mbps, (min(megabits / mbps, p.max_hover_s) if mbps > 0 else p.max_hover_s)

    def _result(self, end, is_paper: bool) -> dict:
        result = {"mission_time_s": end.time, "rescued": len(self.rescues), "rescues": self.rescues}
        if self.energy:
            used = sum(e["energy_wh"] for e in self.energy.values())
            result["energy"] = {ue: {"energy_wh": e["energy_wh"], "soc": e["soc"],
                                     "returned_home": ue in self.returning} for ue, e in self.energy.items()}
            result["energy_per_rescue_wh"] = round(used / len(self.rescues), 4) if self.rescues else None
        if is_paper:
            data = end.data if isinstance(end.data, dict) else {}
            for key in ("mission_time_s", "clock_offset_s", "flight_time_s", "hover_s", "flown_m"):
                if key in data:
                    result[key] = data[key]
        return result
