"""The radio network's UEs as arrays (issue #53): each UE has a column, kept while it stays
(the link levels' and the mobility manager's row too), and what a step needs of it (position,
antenna height, indoor state, last SINR) sits in arrays indexed by column, so a step gathers
them at once instead of a Python loop over UEs. The per-UE reports a step publishes are built
from those arrays in one pass (:func:`ue_reports`), their numbers converted in bulk.
"""

from __future__ import annotations

import itertools
import operator
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

    def place(self, payloads: list[dict[str, Any]], lift_m: float) -> None:
        """The positions of ``payloads`` (``3D.mobility.positions``' messages, in delivery order)
        into :attr:`position`, at once; a UE not yet here is added first (in the order it first
        appears, its antenna ``lift_m`` above its position). A UE with two messages: the last."""
        if not payloads:
            return
        last = {d["UE_Id"]: d for d in payloads}  # (first appearance's order, last message)
        for u, d in last.items():
            if u not in self.ues:
                col = self.add(u, d["UE_type"])  # (first: it may grow the arrays)
                self.arrays["lift"][col] = lift_m
        cols = [self.ues[u]["column"] for u in last]
        xyz = operator.itemgetter("x", "y", "z")
        self.arrays["position"][cols] = [xyz(d["position"]) for d in last.values()]

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
    finite = np.isfinite(np.asarray(values, dtype=float)).tolist()  # (rounding keeps a value finite or not)
    return [r if f else None for r, f in zip(rounded(values, digits), finite, strict=True)]


def link_fields(res: Any, cols: np.ndarray) -> dict[str, np.ndarray]:
    """A link level's results (:class:`~caviar_plugins.radio.link_level.SlotResults`) of the UE
    columns ``cols``, the fields of ``network.ue`` they give."""
    return {"mcs": res.mcs[cols], "tbler": res.tbler[cols], "harq_ack": res.acks[cols],
            "harq_nack": res.nacks[cols], "prbs": res.prbs[cols]}


def _summaries(link: dict[str, np.ndarray], prefix: str = "") -> list[dict[str, Any]]:
    """Every UE's link summary (``mcs``, ``tbler``, ``harq_ack``, ``harq_nack``, ``prbs``)."""
    columns = [link[k].tolist() for k in ("mcs", "harq_ack", "harq_nack", "prbs")]
    columns[1:1] = [rounded(link["tbler"], 4), np.isnan(link["tbler"]).tolist()]
    k_mcs, k_tbler, k_ack, k_nack, k_prbs = (prefix + k for k in ("mcs", "tbler", "harq_ack", "harq_nack", "prbs"))
    return [{k_mcs: m, k_tbler: None if nan else b, k_ack: a, k_nack: n, k_prbs: p}
            for m, b, nan, a, n, p in zip(*columns, strict=True)]


def uplink_fields(tx: np.ndarray, sinr: np.ndarray, mbps: np.ndarray, link: dict[str, np.ndarray]) -> list[dict]:
    """Every UE's ``ul_*`` fields of ``network.ue``: PUSCH power, mean SINR, throughput [ue] and
    the uplink link level's :func:`link_fields`."""
    fields = zip(rounded(tx, 3), _finite(sinr, 3), rounded(mbps, 6),
                 _summaries(link, "ul_"), strict=True)
    return [{"ul_tx_power_dbm": p, "ul_sinr_db": s, "ul_throughput_mbps": m, **rest} for p, s, m, rest in fields]


def ue_reports(names: list[str], ids: list[str], types: list[str], serving: np.ndarray, sinr: np.ndarray,
               sir: np.ndarray, loss: np.ndarray, rsrp: np.ndarray, listed: np.ndarray | None, mbps: np.ndarray,
               link: dict[str, np.ndarray] | None,
               extras: list[dict[str, Any]] | Callable[[int, bool], dict[str, Any]],
               position: np.ndarray) -> Iterator[tuple[str, dict[str, Any]]]:
    """Every UE's ``communications.throughput`` and ``network.ue``, in UE order, from the step's
    arrays ([ue]; ``rsrp`` [ue, cell] and the cells ``listed`` of each UE [ue, k], None: all;
    ``link`` the link level's ``mcs``, ``tbler``, ``harq_ack``, ``harq_nack``, ``prbs`` [ue],
    None for a Shannon link); ``extras``: each UE's fields beyond them (:func:`ue_extras`'s
    list, or ``extras(i, covered)``). The messages are made by list comprehensions over the
    columns, not a function call per UE."""
    covered = (serving >= 0).tolist()
    sinr_l, sir_l, loss_l = _finite(sinr, 3), _finite(sir, 3), rounded(loss, 3)
    mbps_l = rounded(mbps, 6)
    rsrp_l = rounded(rsrp, 2)
    thr = [{"UE_type": t, "UE_Id": u, "throughput": m} for t, u, m in zip(types, ids, mbps_l, strict=True)]
    if listed is None:
        listed_rsrp = [dict(zip(names, r, strict=True)) for r in rsrp_l]
    else:
        listed_rsrp = [dict(zip(map(names.__getitem__, ks), map(r.__getitem__, ks), strict=True))
                       for r, ks in zip(rsrp_l, listed.tolist(), strict=True)]  # (no Python frame a UE)
    # (None where the UE has no cell: no signal, paths gone)
    reports = [{"UE_type": t, "UE_Id": u, "serving_cell": names[s] if c else None, "sinr_db": si if c else None,
                "sir_db": sr if c else None, "coupling_loss_db": lo if c else None, "rsrp_dbm": r,
                "throughput_mbps": m}
               for t, u, s, c, si, sr, lo, r, m in zip(types, ids, serving.tolist(), covered, sinr_l, sir_l, loss_l,
                                                       listed_rsrp, mbps_l, strict=True)]
    dropped = [i for i, t in enumerate(types) if t == "dropped"]
    if dropped:  # (no other module publishes where the network dropped it)
        pos_l = rounded(position[dropped], 2)
        for i, p in zip(dropped, pos_l, strict=True):
            reports[i]["position_m"] = p
    if link is not None:
        for report, summary in zip(reports, _summaries(link), strict=True):
            report.update(summary)
    tails = extras if isinstance(extras, list) else [extras(i, c) for i, c in enumerate(covered)]
    for report, tail in zip(reports, tails, strict=True):
        if tail:
            report.update(tail)
    for a, b in zip(thr, reports, strict=True):
        yield THROUGHPUT, a
        yield NETWORK_UE, b


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
              directions: tuple[str, ...]) -> list[dict[str, Any]]:
    """Every UE's ``network.ue`` fields beyond the downlink's, from the step's arrays, [ue]: for a
    UE with a cell its uplink's (``ul``: :func:`uplink_fields`) and its best beam's on the
    serving cell (``beam_reports[cell][beam]``, ``best_beams`` [ue, cell]), then its queues'
    (those not None). Made by comprehensions; a UE without any shares one empty dict."""
    covered = (serving >= 0).tolist()
    none: dict[str, Any] = {}
    beams: Any = itertools.repeat(none)
    if beam_reports is not None and best_beams is not None:
        sv = np.maximum(serving, 0)
        beams = [beam_reports[s][b] for s, b in
                 zip(sv.tolist(), best_beams[np.arange(len(sv)), sv].tolist(), strict=True)]
    queued: Any = itertools.repeat(none)
    if queues is not None:
        columns = queues.reports(ids, types, directions)
        keys = [name for name, _ in columns]
        present = zip(*([v is not None for v in column] for _, column in columns), strict=True)
        queued = [dict(itertools.compress(zip(keys, row, strict=True), mask))  # (those not None; no frame a UE)
                  for row, mask in zip(zip(*(column for _, column in columns), strict=True), present, strict=True)]
    uls = itertools.repeat(none) if ul is None else ul
    return [{**u, **b, **q} if c else q for c, u, b, q in zip(covered, uls, beams, queued, strict=False)]
