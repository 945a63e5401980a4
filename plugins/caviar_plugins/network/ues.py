"""The radio network's UEs as arrays (issue #53): each UE has a column, kept while it stays
(the link levels' and the mobility manager's row too), and what a step needs of it (position,
antenna height, indoor state, last SINR) sits in arrays indexed by column, so a step gathers
them at once instead of a Python loop over UEs. The per-UE reports a step publishes are built
from those arrays in one pass (:func:`ue_reports`), their numbers converted in bulk.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Iterator

import numpy as np

from caviar_plugins.schema import NETWORK_UE, THROUGHPUT

ARRAYS = {"position": (3,), "lift": (), "indoor": (), "distance_2d_in": (), "last_sinr": ()}
"""Per column: the reported position, the antenna above it (m), indoor (0/1), the 2D distance
indoors (m), the last SINR on the serving cell (NaN: none)."""


class UeTable:
    """UE_Id -> column and type, and the per-column arrays of :data:`ARRAYS`."""

    def __init__(self) -> None:
        self.ues: dict[str, dict[str, Any]] = {}  # UE_Id -> {type, column}
        self.free: list[int] = []
        self.arrays = {name: np.zeros((8, *shape)) for name, shape in ARRAYS.items()}
        self._view: tuple[list[str], np.ndarray, list[str]] | None = None

    def __contains__(self, ue: str) -> bool:
        return ue in self.ues

    def __len__(self) -> int:
        return len(self.ues)

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    def add(self, ue: str, ue_type: str) -> int:
        """A new UE in the first free column (a column its predecessor left starts afresh)."""
        col = self.free.pop(0) if self.free else len(self.ues)
        if col >= len(self.arrays["lift"]):
            for name, a in self.arrays.items():
                grown = np.zeros((max(2 * len(a), col + 1), *a.shape[1:]))
                grown[:len(a)] = a
                self.arrays[name] = grown
        for a in self.arrays.values():
            a[col] = 0.0
        self.arrays["last_sinr"][col] = np.nan
        self.ues[ue] = {"type": ue_type, "column": col}
        self._view = None
        return col

    def pop(self, ue: str) -> int:
        """Removes ``ue``; its column is free again."""
        col = self.ues.pop(ue)["column"]
        self.free.append(col)
        self.free.sort()
        self._view = None
        return col

    def column(self, ue: str) -> int:
        return self.ues[ue]["column"]

    def view(self) -> tuple[list[str], np.ndarray, list[str]]:
        """(UE_Ids, their columns, their types), in the order the UEs came; the same objects
        until a UE comes or goes."""
        if self._view is None:
            ids = list(self.ues)
            self._view = (ids, np.array([self.ues[u]["column"] for u in ids], dtype=np.int64),
                          [self.ues[u]["type"] for u in ids])
        return self._view

    def state(self) -> dict[str, Any]:
        return {"ues": {u: dict(v) for u, v in self.ues.items()}, "free": list(self.free),
                "arrays": {k: a.copy() for k, a in self.arrays.items()}}

    def restore(self, state: dict[str, Any]) -> None:
        self.ues, self.free = state["ues"], state["free"]
        self.arrays = {k: a.copy() for k, a in state["arrays"].items()}
        self._view = None


def rounded(values: np.ndarray, digits: int) -> list:
    """``[round(float(v), digits) for v in values]`` (a nested list for a 2-D array), in bulk:
    Python's ``round`` is the nearest float to the decimal rounding of the exact value (ties to
    even), which ``rint(v·10^d)/10^d`` gives too wherever ``v·10^d`` is not within rounding error
    of a tie; the few that are are rounded by Python. Non-finite values stay as they are."""
    v = np.asarray(values, dtype=float)
    scale = 10.0 ** digits
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = v * scale
        out = np.rint(scaled) / scale
        near_tie = np.abs(np.abs(scaled - np.trunc(scaled)) - 0.5) < 1e-6 + 1e-15 * np.abs(scaled)
        near_tie |= np.abs(scaled) >= 2.0 ** 52  # (beyond float's integers: Python's)
    out = np.where(np.isfinite(v), out, v)
    for i in map(tuple, np.argwhere(near_tie & np.isfinite(v))):
        out[i] = round(float(v[i]), digits)
    return out.tolist()


def _finite(values: np.ndarray, digits: int) -> list[float | None]:
    """Rounded as :func:`~caviar_plugins.network.report.finite` rounds, in bulk (None: not finite)."""
    return [r if math.isfinite(r) else None for r in rounded(values, digits)]


def link_fields(res: Any, cols: np.ndarray) -> dict[str, np.ndarray]:
    """A link level's results (:class:`~caviar_plugins.radio.link_level.SlotResults`) of the UE
    columns ``cols``, the fields of ``network.ue`` they give."""
    return {"mcs": res.mcs[cols], "tbler": res.tbler[cols], "harq_ack": res.acks[cols],
            "harq_nack": res.nacks[cols], "prbs": res.prbs[cols]}


def _summaries(link: dict[str, np.ndarray], prefix: str = "") -> list[dict[str, Any]]:
    """Every UE's link summary (``mcs``, ``tbler``, ``harq_ack``, ``harq_nack``, ``prbs``)."""
    columns = [link[k].tolist() for k in ("mcs", "harq_ack", "harq_nack", "prbs")]
    columns.insert(1, rounded(link["tbler"], 4))
    return [{prefix + "mcs": m, prefix + "tbler": None if math.isnan(b) else b, prefix + "harq_ack": a,
             prefix + "harq_nack": n, prefix + "prbs": p} for m, b, a, n, p in zip(*columns, strict=True)]


def uplink_fields(tx: np.ndarray, sinr: np.ndarray, mbps: np.ndarray, link: dict[str, np.ndarray]) -> list[dict]:
    """Every UE's ``ul_*`` fields of ``network.ue``: PUSCH power, mean SINR, throughput [ue] and
    the uplink link level's :func:`link_fields`."""
    fields = zip(rounded(tx, 3), _finite(sinr, 3), rounded(mbps, 6),
                 _summaries(link, "ul_"), strict=True)
    return [{"ul_tx_power_dbm": p, "ul_sinr_db": s, "ul_throughput_mbps": m, **rest} for p, s, m, rest in fields]


def ue_reports(names: list[str], ids: list[str], types: list[str], serving: np.ndarray, sinr: np.ndarray,
               sir: np.ndarray, loss: np.ndarray, rsrp: np.ndarray, listed: np.ndarray | None, mbps: np.ndarray,
               link: dict[str, np.ndarray] | None, extras: Callable[[int, bool], dict[str, Any]],
               position: np.ndarray) -> Iterator[tuple[str, dict[str, Any]]]:
    """Every UE's ``communications.throughput`` and ``network.ue``, in UE order, from the step's
    arrays ([ue]; ``rsrp`` [ue, cell] and the cells ``listed`` of each UE [ue, k], None: all;
    ``link`` the link level's ``mcs``, ``tbler``, ``harq_ack``, ``harq_nack``, ``prbs`` [ue],
    None for a Shannon link); ``extras(i, covered)``: UE i's fields beyond them."""
    covered = (serving >= 0).tolist()
    cell = [names[s] if c else None for s, c in zip(serving.tolist(), covered, strict=True)]
    sinr_l, sir_l, loss_l = _finite(sinr, 3), _finite(sir, 3), rounded(loss, 3)
    mbps_l = rounded(mbps, 6)
    rsrp_l = rounded(rsrp, 2)
    listed_l = None if listed is None else listed.tolist()
    pos_l = rounded(position, 2)
    summary = None if link is None else _summaries(link)
    for i, u in enumerate(ids):
        ue_type, c, r = types[i], covered[i], rsrp_l[i]
        yield THROUGHPUT, {"UE_type": ue_type, "UE_Id": u, "throughput": mbps_l[i]}
        listed_rsrp = dict(zip(names, r, strict=True)) if listed_l is None else {names[k]: r[k] for k in listed_l[i]}
        report = {"UE_type": ue_type, "UE_Id": u, "serving_cell": cell[i],
                  "sinr_db": sinr_l[i] if c else None,  # (None: no signal, paths gone)
                  "sir_db": sir_l[i] if c else None,
                  "coupling_loss_db": loss_l[i] if c else None,
                  "rsrp_dbm": listed_rsrp,
                  "throughput_mbps": mbps_l[i]}
        if ue_type == "dropped":  # (no other module publishes where the network dropped it)
            report["position_m"] = pos_l[i]
        if summary is not None:
            report.update(summary[i])
        report.update(extras(i, c))
        yield NETWORK_UE, report


def link_columns(per_slot: np.ndarray, serving: np.ndarray, cols: np.ndarray, slots: int):
    """A link level's inputs on UE columns (stable across steps) from the step's UE rows:
    SINR [slot, column, subband] over the step's ``slots`` (``per_slot`` [slot or 1, ue,
    subband]: one row is every slot's), and the serving cell per column (-1: none)."""
    sinr_cols = np.full((len(per_slot), int(cols.max()) + 1, per_slot.shape[2]), np.nan)
    serving_cols = np.full(int(cols.max()) + 1, -1)
    sinr_cols[:, cols], serving_cols[cols] = per_slot, serving
    return np.broadcast_to(sinr_cols, (slots, *sinr_cols.shape[1:])), serving_cols


def run_link(link: Any, per_slot: Any, serving: np.ndarray, cols: np.ndarray, slots: int, backlog: Any = None) -> Any:
    """A link level's call on the step's UE rows, in its UE columns (stable across steps):
    ``per_slot`` [slot or 1, ue, subband] numpy dB (:func:`link_columns`, then
    :meth:`~caviar_plugins.radio.link_level.LinkLevel.run`) or a torch tensor of linear SINRs
    (placed in the columns where it is, then
    :meth:`~caviar_plugins.radio.link_level.LinkLevel.run_linear`: no way through numpy)."""
    if isinstance(per_slot, np.ndarray):
        return link.run(*link_columns(per_slot, serving, cols, slots), backlog=backlog)
    width = int(cols.max()) + 1
    serving_cols = np.full(width, -1)
    serving_cols[cols] = serving
    if width != len(cols) or not np.array_equal(cols, np.arange(width)):  # (columns left free, or out of order)
        from caviar_plugins.torch_device import to_torch

        placed = per_slot.new_full((per_slot.shape[0], width, per_slot.shape[2]), float("nan"))
        placed[:, to_torch(cols, per_slot.device)] = per_slot
        per_slot = placed
    return link.run_linear(per_slot, serving_cols, slots, backlog=backlog)


def ue_extras(ids: list[str], types: list[str], serving: np.ndarray, ul: list[dict] | None,
              beam_reports: list[list[dict]] | None, best_beams: np.ndarray | None, queues: Any,
              directions: tuple[str, ...]) -> Callable[[int, bool], dict[str, Any]]:
    """``extras(i, covered)``: UE ``i``'s ``network.ue`` fields beyond the downlink's, from the
    step's arrays: its uplink's (``ul``: :func:`uplink_fields`), its best beam's on the serving
    cell (``beam_reports[cell][beam]``, ``best_beams`` [ue, cell]) and its queues'."""
    beams: list[dict] | None = None
    if beam_reports is not None and best_beams is not None:
        sv = np.maximum(serving, 0)
        beams = [beam_reports[s][b] for s, b in
                 zip(sv.tolist(), best_beams[np.arange(len(sv)), sv].tolist(), strict=True)]

    queued = None if queues is None else queues.reports(ids, types, directions)

    def extras(i: int, covered: bool) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if ul is not None and covered:
            out.update(ul[i])
        if beams is not None and covered:
            out.update(beams[i])
        for name, column in queued or ():
            if column[i] is not None:
                out[name] = column[i]
        return out
    return extras
