"""Load on the radio network: what each UE has to send and receive, queued and served.

Per UE and direction (downlink, and the uplink when it is on) the traffic is

- ``full-buffer``: always data to send (the default; the 3GPP calibration's assumption);
- ``ftp3``: 3GPP FTP model 3, files of ``ftp.file_bytes`` (0.5 MB by default) arriving as
  a Poisson process of rate ``ftp.arrival_rate_hz`` per UE (TR 36.872 Annex A, the
  system-level evaluation assumptions of TR 36.814 / 38.802);
- ``none``: nothing of its own, only what it carries (below).

A UE also carries **messages the twin publishes**: each ``carry`` entry names a topic pattern
(``3D.camera.*``: the camera images) whose messages are queued, bytes and all, at the UE that
published them (the payload's ``UE_Id``, else the topic's last token) as they are produced.
Once the network has delivered a message's last byte it is published again on
``deliver_to.<UE_Id>`` (``ai.images.uav1``), unchanged, for the module that reads it there:
the detector sees an image only once the uplink has carried it.

Each UE's queue is served by strict priority (a ``carry`` entry's ``priority``, higher first;
FTP files 0), first in, first out within a priority, as a MAC serves its logical channels
by priority (TS 38.321 §5.4.3.1, without prioritised bit rates). The link level serves only UEs with bytes queued
(:class:`Backlog`); what it decodes in a slot leaves the head of the queue. A transfer that
completes is published on ``network.transfers``: its delay from queued to fully delivered
and its user-perceived throughput (bits over that delay, TR 36.814's definition).
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from typing import Any

import numpy as np

from caviar.errors import ConfigWarning
from caviar.topics import matches
from caviar_plugins.schema import UE_TYPES, fields_of

MODELS = ("full-buffer", "ftp3", "none")
DIRECTIONS = ("downlink", "uplink")


@dataclasses.dataclass
class FtpSettings:
    """3GPP FTP model 3: files of one size, arriving per UE as a Poisson process."""

    file_bytes: float = 512_000.0
    """File size in bytes: 0.5 Mbyte, the 3GPP evaluations' size."""
    arrival_rate_hz: float = 1.0
    """λ, files per second per UE and direction (the offered load is λ · file size)."""

    def __post_init__(self):
        if not self.file_bytes > 0:
            raise ValueError(f"file_bytes: expected a file size > 0 bytes, got {self.file_bytes!r}")
        if not self.arrival_rate_hz > 0:
            raise ValueError(f"arrival_rate_hz: expected a Poisson arrival rate > 0 per second, "
                             f"got {self.arrival_rate_hz!r}")


@dataclasses.dataclass
class Carried:
    """Messages of the twin that a UE sends (uplink) or receives (downlink) over the network."""

    topic: str
    """A topic pattern (``3D.camera.*``); its messages are queued at the UE that published them."""
    direction: str = "uplink"
    deliver_to: str | None = None
    """Republish each delivered message on ``deliver_to.<UE_Id>`` (None: only account for it)."""
    size_field: str | None = None
    """A payload field giving the message's size in bytes (``bytes``); by default its own size
    (an array's bytes, a byte string's length, a JSON payload's text)."""
    priority: int = 0
    """Served before the UE's queued transfers of lower priority (FTP files: 0)."""

    def __post_init__(self):
        try:
            matches(self.topic, "x")
        except ValueError as e:
            raise ValueError(f"topic: {e}") from None
        if self.direction not in DIRECTIONS:
            raise ValueError(f"direction: expected one of {list(DIRECTIONS)}, got {self.direction!r}")
        if self.deliver_to is not None:
            try:
                matches(self.deliver_to + ".x", "x")
            except ValueError as e:
                raise ValueError(f"deliver_to: expected a topic prefix, {e}") from None
        if self.size_field is not None:
            for topic, fields in fields_of(self.topic).items():  # (the topics whose payloads are known)
                if fields is None:
                    raise ValueError(f"size_field: {topic}'s payloads are binary, without fields; leave size_field "
                                     f"out to count their bytes")
                if self.size_field not in fields:
                    raise ValueError(f"size_field: {topic}'s payloads have no field {self.size_field!r}; "
                                     f"they have {', '.join(fields)}")


@dataclasses.dataclass
class TrafficSettings:
    """Each UE's own load per direction (``full-buffer``, ``ftp3`` or ``none``) and the twin's
    messages the UEs carry."""

    downlink: str = "full-buffer"
    uplink: str = "full-buffer"
    """The uplink's load, when the network simulates the uplink (``uplink = {...}``)."""
    ftp: FtpSettings = dataclasses.field(default_factory=FtpSettings)
    carry: list[Carried] = dataclasses.field(default_factory=list)
    """Topics whose messages go over the network (``[{ topic = "3D.camera.*", deliver_to =
    "ai.images" }]``)."""
    by_type: dict[str, dict[str, str]] = dataclasses.field(default_factory=dict)
    """Another load for the UEs of a type (``{ UAV = { downlink = "none" } }``: the UAVs
    download nothing while the cars run FTP); a direction not named keeps the default."""

    def __post_init__(self):
        for key in DIRECTIONS:
            if getattr(self, key) not in MODELS:
                raise ValueError(f"{key}: expected one of {list(MODELS)}, got {getattr(self, key)!r}")
        for ue_type, models in self.by_type.items():
            if not isinstance(models, dict):
                raise ValueError(f"by_type.{ue_type}: expected a table of downlink and uplink, got {models!r}")
            for key, model in models.items():
                if key not in DIRECTIONS or model not in MODELS:
                    raise ValueError(f"by_type.{ue_type}.{key}: expected downlink or uplink set to one of "
                                     f"{list(MODELS)}, got {key} = {model!r}")
            if ue_type not in UE_TYPES:
                warnings.warn(ConfigWarning(f"no shipped module publishes UEs of type {ue_type!r} (they publish "
                                            f"{', '.join(UE_TYPES)}); unless a module of yours does, this load "
                                            f"applies to no UE", f"by_type.{ue_type}"), stacklevel=2)

    def model(self, direction: str, ue_type: str | None = None) -> str:
        """The load of a UE of ``ue_type`` in ``direction``."""
        return self.by_type.get(ue_type or "", {}).get(direction, getattr(self, direction))

    @property
    def full_buffer(self) -> bool:
        """Every UE has data at all times in both directions (no queues to keep)."""
        models = {self.downlink, self.uplink} | {m for t in self.by_type.values() for m in t.values()}
        return models == {"full-buffer"} and not self.carry


def payload_bytes(data: Any, size_field: str | None) -> int:
    """A message's size in bytes: its ``size_field``, else the payload's own size (a
    ValueError ``size_field: …`` for a payload without that field, or not a size there)."""
    if size_field is not None:
        if not isinstance(data, dict) or size_field not in data:
            raise ValueError(f"size_field: the payload has no field {size_field!r}"
                             + (f" (its fields: {', '.join(map(str, data))})" if isinstance(data, dict) else
                                f" (it is {type(data).__name__}, not a table)"))
        size = data[size_field]
        if isinstance(size, bool) or not isinstance(size, (int, float)) or not 0 <= size < 2 ** 53:
            raise ValueError(f"size_field: the payload's {size_field!r} is {size!r}, not a size in bytes")
        return int(size)
    if isinstance(data, np.ndarray):
        return int(data.nbytes)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return len(data)
    return len(json.dumps(data, separators=(",", ":")).encode())


@dataclasses.dataclass
class Transfer:
    """One file or message in a UE's queue."""

    ue: str
    direction: str
    source: str
    """``ftp`` or the topic it was published on."""
    queued_s: float
    size_bytes: int
    left_bits: float
    payload: Any = None
    deliver_to: str | None = None
    arrival_slot: int = -1
    """The slot of the current step it arrives in (-1: queued before the step's first slot)."""
    priority: int = 0


@dataclasses.dataclass
class Backlog:
    """What a link level may serve in one call, per UE column: bits queued at the first
    slot (``inf``: full buffer) and bits arriving at the start of each slot."""

    queued_bits: np.ndarray  # [n_ue]
    arrivals_bits: np.ndarray  # [n_slots, n_ue]


class Queues:
    """Every UE's transfers per direction, FTP arrivals drawn from its own stream."""

    def __init__(self, settings: TrafficSettings, seed: int):
        self.s = settings
        self.rng = np.random.default_rng([seed, 36872])
        self.queues: dict[tuple[str, str], list[Transfer]] = {}
        self.next_file: dict[tuple[str, str], float] = {}  # (UE, direction) -> next FTP arrival (s)
        self.lost: list[Transfer] = []  # transfers of UEs that left, to report (:meth:`finished`)
        # Per step's UEs (the same list objects until a UE comes or goes): each row's model per
        # direction, each UE's row, each row's next FTP arrival (NaN: none drawn yet) per direction.
        self._rows: dict[str, Any] = {}

    def state(self) -> dict[str, Any]:
        return {"rng": self.rng.bit_generator.state, "queues": self.queues, "next_file": self.next_file,
                "lost": self.lost}

    def restore(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.queues, self.next_file, self.lost = state["queues"], state["next_file"], state["lost"]
        self._rows = {}

    def step_backlog(self, t: float, ids: list[str], types: list[str], direction: str, slots: int, slot_s: float,
                     scheduled: bool) -> tuple[Backlog | None, np.ndarray | None]:
        """A step's :meth:`backlog` of ``ids`` in ``direction`` (None: every UE has a full
        buffer) and, with ``scheduled`` interference, which UEs have any bits: the only ones
        their cells transmit to or receive from ([ue] bool; None: all, as under full-buffer
        interference)."""
        if all(self.model(direction, k) == "full-buffer" for k in set(types)):
            return None, None
        backlog = self.backlog(t, ids, types, direction, slots, slot_s)
        if not scheduled:
            return backlog, None  # (every cell transmits, whatever its queues)
        return backlog, (backlog.queued_bits > 0) | (backlog.arrivals_bits > 0).any(axis=0)

    def finished(self, t: float, ids: list[str], direction: str, delivered_bits: np.ndarray,
                 slot_s: float) -> list[tuple[Transfer, float | None]]:
        """The transfers the UEs that left did not finish (done: None; once) and those the
        step's delivered bits completed (:meth:`serve`), in that order."""
        lost, self.lost = [(x, None) for x in self.lost], []
        return lost + list(self.serve(t, ids, direction, delivered_bits, slot_s))

    def model(self, direction: str, ue_type: str | None = None) -> str:
        return self.s.model(direction, ue_type)

    def queue_message(self, t: float, ue: str, topic: str, data: Any, carried: Carried) -> None:
        size = payload_bytes(data, carried.size_field)
        self._enqueue(Transfer(ue, carried.direction, topic, t, size, 8.0 * size, data, carried.deliver_to,
                               priority=carried.priority))

    def _enqueue(self, x: Transfer) -> None:
        """Behind the transfers of its priority and above, ahead of those below."""
        queue = self.queues.setdefault((x.ue, x.direction), [])
        at = next((i for i, y in enumerate(queue) if y.priority < x.priority), len(queue))
        queue.insert(at, x)

    def forget(self, ue: str) -> list[Transfer]:
        """Drops a UE that left; returns the transfers it had not finished (and keeps them
        for :meth:`finished` to report)."""
        left = []
        for d in DIRECTIONS:
            left += self.queues.pop((ue, d), [])
            self.next_file.pop((ue, d), None)
        self.lost += left
        self._rows = {}
        return left

    def _of_rows(self, key: str, ids: list[str], types: list[str] | None, make: Any) -> Any:
        """What ``make()`` gives for these rows, made once while the step's UEs stay the same
        objects (the network's :meth:`~caviar_plugins.network.ues.UeTable.view`)."""
        held = self._rows.get(key)
        if held is None or held[0] is not ids or held[1] is not types:
            held = self._rows[key] = (ids, types, make())
        return held[2]

    def _models(self, ids: list[str], types: list[str], direction: str) -> np.ndarray:
        """[row]: each UE's load in ``direction`` (one look-up per UE type)."""
        def make() -> np.ndarray:
            of_type = {k: self.model(direction, k) for k in set(types)}
            return np.array([of_type[k] for k in types], dtype=object)
        return self._of_rows("models " + direction, ids, types, make)

    def _queued_rows(self, ids: list[str], direction: str) -> list[tuple[int, list[Transfer]]]:
        """(row, queue) of the UEs with transfers queued in ``direction``, in row order: what a
        step's queue work goes through (not every UE)."""
        rows = self._of_rows("rows", ids, None, lambda: {u: i for i, u in enumerate(ids)})
        found = [(rows[u], q) for (u, d), q in self.queues.items() if d == direction and q and u in rows]
        return sorted(found, key=lambda x: x[0])

    def backlog(self, t: float, ids: list[str], types: list[str], direction: str, slots: int,
                slot_s: float) -> Backlog:
        """The step's :class:`Backlog` of UEs ``ids`` (rows, of ``types``) in ``direction``:
        queued bits (a full buffer: unbounded), and FTP files arriving in the step's slots
        [t, t + slots·slot_s) (queued as they arrive). Work per UE with a file due or bits
        queued, not per UE: the next arrivals are an array, compared at once."""
        queued = np.zeros(len(ids))
        arrivals = np.zeros((slots, len(ids)))
        end = t + slots * slot_s
        models = self._models(ids, types, direction)
        full = models == "full-buffer"
        queued[full] = math.inf
        ftp = np.flatnonzero(models == "ftp3")
        if len(ftp):
            next_at = self._of_rows("next " + direction, ids, types, lambda: np.array(
                [self.next_file.get((u, direction), np.nan) for u in ids]))
            rate, size = self.s.ftp.arrival_rate_hz, self.s.ftp.file_bytes
            # Each FTP UE draws one arrival a step (a first one, or one it discards: the stream as it
            # always was), then each file it gets: its row's draw after those of the rows before it.
            # The rows in between draw theirs at once.
            drawn = 0
            for j in np.flatnonzero(~(next_at[ftp] >= end)).tolist():  # (due, or none drawn yet)
                first = float(self.rng.exponential(1 / rate, size=j - drawn + 1)[-1])
                drawn, i = j + 1, int(ftp[j])
                u = ids[i]
                at = self.next_file.setdefault((u, direction), t + first)
                while at < end:
                    slot = min(max(int((at - t) // slot_s), 0), slots - 1)
                    self._enqueue(Transfer(u, direction, "ftp", at, int(size), 8.0 * int(size), arrival_slot=slot))
                    at += self.rng.exponential(1 / rate)
                self.next_file[(u, direction)] = next_at[i] = at
            if drawn < len(ftp):
                self.rng.exponential(1 / rate, size=len(ftp) - drawn)
        for i, queue in self._queued_rows(ids, direction):
            if full[i]:
                continue
            for x in queue:
                if x.arrival_slot < 0:
                    queued[i] += x.left_bits
                else:
                    arrivals[x.arrival_slot, i] += x.left_bits
        return Backlog(queued, arrivals)

    def serve(self, t: float, ids: list[str], direction: str, delivered_bits: np.ndarray,
              slot_s: float) -> list[tuple[Transfer, float]]:
        """Takes what the link level delivered ([slot, UE row] bits) off the queues' heads;
        returns the transfers completed and when (the end of the slot their last bit was in),
        in row order. Work per UE with transfers queued."""
        done = []
        for i, queue in self._queued_rows(ids, direction):
            for k in np.flatnonzero(delivered_bits[:, i] > 0).tolist():
                bits = float(delivered_bits[k, i])
                while bits > 0:
                    # the first in priority order that has arrived (the link level counted no other)
                    at = next((j for j, x in enumerate(queue) if x.arrival_slot <= k), None)
                    if at is None:
                        break
                    head = queue[at]
                    taken = min(bits, head.left_bits)
                    head.left_bits -= taken
                    bits -= taken
                    if head.left_bits <= 1e-6:
                        queue.pop(at)
                        done.append((head, t + (k + 1) * slot_s))
            for x in queue:  # (waiting at the next step's first slot)
                x.arrival_slot = -1
        return done

    def reports(self, ids: list[str], types: list[str], directions: tuple[str, ...]) -> list[tuple[str, list]]:
        """Every UE's :meth:`report` at once, a column per direction: (``dl_queue_bytes`` or
        ``ul_queue_bytes``, [row] bytes, None for a full buffer). The bytes of the UEs with
        transfers queued are summed, the others' are 0."""
        columns = []
        for d in directions:
            queued = np.zeros(len(ids), dtype=np.int64)
            for i, queue in self._queued_rows(ids, d):
                queued[i] = int(round(sum(x.left_bits for x in queue) / 8))
            full = self._models(ids, types, d) == "full-buffer"
            columns.append((d[0] + "l_queue_bytes", [None if f else q for f, q in zip(full.tolist(), queued.tolist(),
                                                                                    strict=True)]))
        return columns

    def report(self, ue: str, ue_type: str, directions: tuple[str, ...]) -> dict[str, int]:
        """``network.ue``'s ``dl_queue_bytes`` / ``ul_queue_bytes`` (none for a full buffer)."""
        queued = {d[0] + "l_queue_bytes": self.queued_bytes(ue, d, ue_type) for d in directions}
        return {k: v for k, v in queued.items() if v is not None}

    def queued_bytes(self, ue: str, direction: str, ue_type: str | None = None) -> int | None:
        """Bytes waiting at ``ue`` in ``direction`` (None: full buffer)."""
        if self.model(direction, ue_type) == "full-buffer":
            return None
        return int(round(sum(x.left_bits for x in self.queues.get((ue, direction), [])) / 8))


def in_columns(backlog: Backlog | None, cols: np.ndarray) -> Backlog | None:
    """A backlog of UE rows on a link level's UE columns ``cols`` (no bits in the others)."""
    if backlog is None:
        return None
    width = int(cols.max()) + 1
    queued, arrivals = np.zeros(width), np.zeros((backlog.arrivals_bits.shape[0], width))
    queued[cols], arrivals[:, cols] = backlog.queued_bits, backlog.arrivals_bits
    return Backlog(queued, arrivals)


def transfer_record(x: Transfer, done_s: float | None) -> dict[str, Any]:
    """``network.transfers``: a completed file or message, its delay and user-perceived
    throughput; or (``done_s`` None) one its UE left unfinished, with the bytes it still had."""
    record = {"UE_Id": x.ue, "direction": x.direction, "source": x.source, "bytes": x.size_bytes,
              "queued_s": round(x.queued_s, 6)}
    if done_s is None:
        return {**record, "lost": True, "bytes_left": int(math.ceil(x.left_bits / 8))}
    delay = max(done_s - x.queued_s, 1e-12)
    return {**record, "delivered_s": round(done_s, 6), "delay_s": round(delay, 6),
            "upt_mbps": round(8 * x.size_bytes / delay / 1e6, 6)}
