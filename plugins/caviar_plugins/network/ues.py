"""The radio network's UEs as arrays (issue #53): each UE has a column, kept while it stays
(the link levels' and the mobility manager's row too), and what a step needs of it (position,
antenna height, indoor state, last SINR) sits in arrays indexed by column, so a step gathers
them at once instead of a Python loop over UEs. The per-UE reports a step publishes are built
from those arrays in one pass (:func:`ue_reports`), their numbers converted in bulk.
"""

from __future__ import annotations

import itertools
import math
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
        self._column: dict[str, int] = {}  # UE_Id -> column (the same, for lookups in bulk)
        self.free: list[int] = []
        self.arrays = {name: np.zeros((8, *shape)) for name, shape in ARRAYS.items()}
        self._view: tuple[list[str], np.ndarray, list[str]] | None = None
        self._placed: tuple[list[str] | None, np.ndarray | None] = (None, None)  # (a step's UE_Ids, columns)

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
        self._column[ue] = col
        self._view, self._placed = None, (None, None)
        return col

    def place(self, payloads: list[dict[str, Any]], lift_m: float) -> None:
        """The positions of ``payloads`` (``3D.mobility.positions``' messages, in delivery order)
        into :attr:`position`, at once; a UE not yet here is added first (in the order it first
        appears, its antenna ``lift_m`` above its position). A UE with two messages: the last."""
        if not payloads:
            return
        ids = list(map(operator.itemgetter("UE_Id"), payloads))
        if ids == self._placed[0]:  # (the last step's UEs in its order, each once: their columns as they were)
            cols, values = self._placed[1], payloads
        else:
            last = dict(zip(ids, payloads, strict=True))  # (first appearance's order, last message)
            if not last.keys() <= self.ues.keys():  # (a set test: the UEs are known but in a step that adds one)
                for u, d in last.items():
                    if u not in self.ues:
                        col = self.add(u, d["UE_type"])  # (first: it may grow the arrays)
                        self.arrays["lift"][col] = lift_m
            cols = np.fromiter(map(self._column.__getitem__, last), dtype=np.int64, count=len(last))
            values = list(last.values())
            self._placed = (ids if len(last) == len(ids) else None, cols)
        xyz = map(operator.itemgetter("x", "y", "z"), map(operator.itemgetter("position"), values))
        try:
            at = np.fromiter(itertools.chain.from_iterable(xyz), dtype=float, count=3 * len(values)).reshape(-1, 3)
            bad = np.flatnonzero(~np.isfinite(at).all(axis=1)).tolist()
        except (TypeError, ValueError):  # (a coordinate that is not a number at all)
            bad = [i for i, d in enumerate(values) if not _finite_xyz(d["position"])]
        if bad:  # (None, NaN, a string: which UE's, before it reaches the channel)
            d = values[bad[0]]
            raise ValueError(f"3D.mobility.positions: UE {d['UE_Id']!r} is at {d['position']}: expected finite "
                             "numbers x, y and z (metres)")
        self.arrays["position"][cols] = at

    def pop(self, ue: str) -> int:
        """Removes ``ue``; its column is free again."""
        col = self.ues.pop(ue)["column"]
        del self._column[ue]
        self.free.append(col)
        self.free.sort()
        self._view, self._placed = None, (None, None)
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
        self._column = {u: v["column"] for u, v in self.ues.items()}
        self.arrays = {k: a.copy() for k, a in state["arrays"].items()}
        self._view, self._placed = None, (None, None)


def _finite_xyz(position: dict[str, Any]) -> bool:
    """Whether a position payload's x, y and z are finite numbers."""
    try:
        return bool(np.isfinite(np.array([position[k] for k in "xyz"], dtype=float)).all())
    except (TypeError, ValueError):
        return False


def rounded(values: np.ndarray, digits: int) -> list:
    """``[round(float(v), digits) for v in values]`` (a nested list for a 2-D array), in bulk:
    :func:`rounded_array`'s numbers as Python floats."""
    return rounded_array(values, digits).tolist()


def rounded_array(values: np.ndarray, digits: int) -> np.ndarray:
    """``round(float(v), digits)`` of every ``v``, in bulk, as a float64 array: Python's ``round``
    is the nearest float to the decimal rounding of the exact value (ties to even), which
    ``rint(v·10^d)/10^d`` gives too wherever ``v·10^d`` is not within rounding error of a tie;
    those that may be (a fraction within 2e-6 of one half, or beyond 1e10, where ``v·10^d``'s own
    error may reach 1.1e-6) are rounded by Python.
    Non-finite values stay as they are (``rint`` and the division keep them)."""
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = v * 10.0 ** digits
        whole = np.rint(scaled)
        out = whole / 10.0 ** digits
        whole -= scaled  # (exact: the distance to the nearest integer, at most one half)
        near_tie = np.abs(whole, out=whole) > 0.5 - 2e-6
        near_tie |= np.abs(scaled, out=scaled) >= 1e10  # (inf too: left as it is below)
    for i in map(tuple, np.argwhere(near_tie)):
        x = float(v[i])
        if math.isfinite(x):
            out[i] = round(x, digits)
    return out


def _finite(values: np.ndarray, digits: int) -> list[float | None]:
    """Rounded as :func:`~caviar_plugins.network.report.finite` rounds, in bulk (None: not finite)."""
    return _listed(rounded_array(values, digits))


def link_fields(res: Any, cols: np.ndarray) -> dict[str, np.ndarray]:
    """A link level's results (:class:`~caviar_plugins.radio.link_level.SlotResults`) of the UE
    columns ``cols``, the fields of ``network.ue`` they give."""
    return {"mcs": res.mcs[cols], "tbler": res.tbler[cols], "harq_ack": res.acks[cols],
            "harq_nack": res.nacks[cols], "prbs": res.prbs[cols]}


def _link_columns(link: dict[str, np.ndarray], prefix: str = "") -> dict[str, list]:
    """Every UE's link summary (``mcs``, ``tbler``, ``harq_ack``, ``harq_nack``, ``prbs``) as
    columns (``tbler`` None for a UE not scheduled)."""
    return {k: _listed(v) for k, v in _link_arrays(link, prefix).items()}


def _listed(values: np.ndarray) -> list:
    """An array as a list, None where a float is not finite."""
    out = values.tolist()
    if values.dtype.kind == "f":
        for i in np.flatnonzero(~np.isfinite(values)).tolist():
            out[i] = None
    return out


def _summaries(link: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Every UE's downlink summary (:func:`_link_columns`), a dict each (literal keys: no
    ``dict(zip(...))`` a UE)."""
    return [{"mcs": m, "tbler": b, "harq_ack": a, "harq_nack": n, "prbs": p}
            for m, b, a, n, p in zip(*_link_columns(link).values(), strict=True)]


def uplink_columns(arrays: dict[str, np.ndarray]) -> dict[str, list]:
    """Every UE's ``ul_*`` fields of ``network.ue`` as lists (None where not finite), from
    :func:`uplink_arrays`."""
    return {k: _listed(v) for k, v in arrays.items()}


def uplink_fields(columns: dict[str, list]) -> list[dict]:
    """Every UE's ``ul_*`` fields of ``network.ue`` from :func:`uplink_columns`, a dict each
    (literal keys: no ``dict(zip(...))`` a UE)."""
    return [{"ul_tx_power_dbm": p, "ul_sinr_db": s, "ul_throughput_mbps": t, "ul_mcs": m, "ul_tbler": b,
             "ul_harq_ack": a, "ul_harq_nack": n, "ul_prbs": r}
            for p, s, t, m, b, a, n, r in zip(*columns.values(), strict=True)]


def throughput_reports(ids: list[str], types: list[str], mbps: np.ndarray | list[float]) -> list[dict[str, Any]]:
    """Every UE's ``communications.throughput`` (the paper's schema), Mbit/s rounded to 6 digits
    (``mbps`` a list: rounded already)."""
    mbps_l = mbps if isinstance(mbps, list) else rounded(mbps, 6)
    return [{"UE_type": t, "UE_Id": u, "throughput": m} for t, u, m in zip(types, ids, mbps_l, strict=True)]


def throughput_messages(ids: list[str], types: list[str], mbps: np.ndarray) -> list[tuple[str, dict[str, Any]]]:
    """:func:`throughput_reports` as the step's messages, (topic, payload) each."""
    return [(THROUGHPUT, x) for x in throughput_reports(ids, types, mbps)]


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
    thr = throughput_reports(ids, types, mbps_l)
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


def ue_table(names: list[str], ids: list[str], types: list[str], serving: np.ndarray, sinr: np.ndarray,
             sir: np.ndarray, loss: np.ndarray, rsrp: np.ndarray, listed: np.ndarray | None, mbps: np.ndarray,
             link: dict[str, np.ndarray] | None, ul: dict[str, np.ndarray] | None,
             beams: dict[str, np.ndarray] | None, queued: list[tuple[str, list]], position: np.ndarray) -> Any:
    """``network.ues``: the step's ``network.ue`` reports as one table (a ``polars.DataFrame``,
    which travels and is recorded in Arrow's format), a column a field and a row a UE
    (``ue_reports = "table"``): the same numbers as :func:`ue_reports`' messages, made by array
    operations, with no Python object a number. Null where a UE's report has None or leaves the
    field out (the uplink's and the serving beam's fields of a UE without a cell, a full
    buffer's queue, the position of a UE the layout did not drop). ``rsrp_dbm`` is a struct a
    row, a field a cell (by its name; with ``report_cells``, null but in the cells listed).
    ``link``: :func:`link_fields`;
    ``ul``: :func:`uplink_arrays`; ``beams``: :func:`beam_columns`; ``queued``: the queues'
    (name, column) pairs. :func:`table_rows` gives the reports back."""
    import polars as pl

    blank = serving < 0  # (no cell)
    serving_names = np.array([*names, None], dtype=object)[serving].tolist()  # (-1: None, no cell)
    # (the columns in the order of a network.ue report's fields)
    columns: dict[str, Any] = {
        "UE_type": types, "UE_Id": ids, "serving_cell": pl.Series("serving_cell", serving_names, dtype=pl.String),
        "sinr_db": _nulls(sinr, 3, blank), "sir_db": _nulls(sir, 3, blank),
        "coupling_loss_db": _nulls(loss, 3, blank)}
    values = rounded_array(rsrp, 2)
    if listed is not None:  # (the cells not listed: null)
        values = np.full_like(values, np.nan)
        rows = np.arange(len(values))[:, None]
        values[rows, listed] = rounded_array(rsrp[rows, listed], 2)
    # (column-major: polars takes each cell's column as it lies)
    rsrp_table = pl.from_numpy(np.asfortranarray(values), schema=names, orient="row")
    if np.isnan(values).any():  # (the cells not listed, or no number: null)
        rsrp_table = rsrp_table.fill_nan(None)
    columns["rsrp_dbm"] = rsrp_table.to_struct("rsrp_dbm")
    columns["throughput_mbps"] = rounded_array(mbps, 6)
    if "dropped" in types:  # (a list: polars sets no null in an array column)
        where = [p if t == "dropped" else None for p, t in zip(rounded(position, 2), types, strict=True)]
        columns["position_m"] = pl.Series(where, dtype=pl.Array(pl.Float64, 3))
    if link is not None:
        columns.update(_link_arrays(link))
    for more in (ul, beams):
        for k, v in (more or {}).items():
            columns[k] = _nulls(v, None, blank)
    columns.update({k: pl.Series(k, v, dtype=pl.Int64) for k, v in queued})
    return pl.DataFrame(columns, nan_to_null=True)


def _nulls(values: np.ndarray, digits: int | None, blank: np.ndarray) -> Any:
    """A column of ``values`` (rounded to ``digits``; None: as they are) with nulls where not
    finite or ``blank``: a float array with NaN there (the table's ``nan_to_null``), or an integer
    Series with nulls."""
    import polars as pl

    v = np.asarray(values)
    if v.dtype.kind in "iu":
        return pl.Series(v.astype(np.int64)).scatter(np.flatnonzero(blank), None) if blank.any() else v
    out = rounded_array(v, digits) if digits is not None else v.astype(float)
    return np.where(blank | ~np.isfinite(out), np.nan, out)


def _link_arrays(link: dict[str, np.ndarray], prefix: str = "") -> dict[str, np.ndarray]:
    """:func:`_link_columns` as arrays: ``tbler`` rounded (NaN: not scheduled), the counts as they are."""
    return {prefix + "mcs": np.asarray(link["mcs"], dtype=np.int64), prefix + "tbler": rounded_array(link["tbler"], 4),
            **{prefix + k: np.asarray(link[k], dtype=np.int64) for k in ("harq_ack", "harq_nack", "prbs")}}


def uplink_arrays(tx: np.ndarray, sinr: np.ndarray, mbps: np.ndarray, link: dict[str, np.ndarray]) -> dict[str, Any]:
    """Every UE's ``ul_*`` fields of ``network.ue`` as arrays: PUSCH power, mean SINR,
    throughput [ue] and the uplink link level's :func:`link_fields`, rounded as reported (NaN: none)."""
    return {"ul_tx_power_dbm": rounded_array(tx, 3), "ul_sinr_db": rounded_array(sinr, 3),
            "ul_throughput_mbps": rounded_array(mbps, 6), **_link_arrays(link, "ul_")}


def table_rows(table: Any) -> list[dict[str, Any]]:
    """A ``network.ues`` table as the ``network.ue`` reports it holds, a dict a UE, as
    :func:`ue_reports` makes them (``rsrp_dbm`` a dict by cell; the fields a report leaves
    out, out)."""
    data = table.to_dict(as_series=False)
    data["rsrp_dbm"] = [{c: v for c, v in r.items() if v is not None} for r in data["rsrp_dbm"]]
    n = len(data["UE_Id"])
    covered = [s is not None for s in data["serving_cell"]]
    rows = []
    for i in range(n):
        row: dict[str, Any] = {}
        for key, column in data.items():
            v = column[i]
            if key in QUEUE_FIELDS or key == "position_m":
                if v is None:
                    continue  # (a full buffer's queue, a UE not dropped: left out)
            elif not covered[i] and (key.startswith(("ul_", "beam_")) or key == "ssb_beam"):
                continue  # (no cell: no uplink, no serving beam)
            row[key] = v
        rows.append(row)
    return rows


QUEUE_FIELDS = ("dl_queue_bytes", "ul_queue_bytes")
"""``network.ue``'s queue fields (a full buffer's: none)."""


def beam_table(beam_reports: list[list[dict]]) -> dict[str, np.ndarray]:
    """The beams' ``network.ue`` fields (``beam_reports[cell][beam]``) as arrays [cell, beam], made
    once (the cells' codebooks may differ in size: the shorter padded, never picked)."""
    keys = list(beam_reports[0][0]) if beam_reports and beam_reports[0] else []
    size = max(len(cell) for cell in beam_reports)
    table = {}
    for k in keys:
        table[k] = np.zeros((len(beam_reports), size), dtype=type(beam_reports[0][0][k]))
        for c, cell in enumerate(beam_reports):
            table[k][c, :len(cell)] = [b[k] for b in cell]
    return table


def beam_columns(table: dict[str, np.ndarray], serving: np.ndarray, best_beams: np.ndarray) -> dict[str, np.ndarray]:
    """Every UE's serving beam's ``network.ue`` fields from :func:`beam_table` and ``best_beams``
    [ue, cell], as arrays (a UE without a cell: its cell 0's, for :func:`ue_table` to blank)."""
    sv = np.maximum(serving, 0)
    best = best_beams[np.arange(len(sv)), sv]
    return {k: by_cell[sv, best] for k, by_cell in table.items()}


def link_columns(per_slot: np.ndarray, serving: np.ndarray, cols: np.ndarray, slots: int):
    """A link level's inputs on UE columns (stable across steps) from the step's UE rows:
    SINR [slot, column, subband] over the step's ``slots`` (``per_slot`` [slot or 1, ue,
    subband]: one row is every slot's), and the serving cell per column (-1: none)."""
    sinr_cols = np.full((len(per_slot), int(cols.max()) + 1, per_slot.shape[2]), np.nan)
    serving_cols = np.full(int(cols.max()) + 1, -1)
    sinr_cols[:, cols], serving_cols[cols] = per_slot, serving
    return np.broadcast_to(sinr_cols, (slots, *sinr_cols.shape[1:])), serving_cols


def run_links(link: Any, per_slots: list, serving: np.ndarray, cols: np.ndarray, slots: int,
              backlogs: list | None = None) -> list:
    """A link level's call on the step's UE rows, in its UE columns (stable across steps), for
    each of its links (downlink, then uplink): ``per_slots``, each [slot or 1, ue, subband], numpy
    dB (placed by :func:`link_columns`) or a torch tensor of linear SINRs (placed in the columns
    where it is: no way through numpy); then
    :meth:`~caviar_plugins.radio.link_level.LinkLevel.run_links`. Each link's results."""
    width = int(cols.max()) + 1
    serving_cols = np.full(width, -1)
    serving_cols[cols] = serving
    moved = width != len(cols) or not np.array_equal(cols, np.arange(width))  # (columns left free, or out of order)
    placed = []
    for per_slot in per_slots:
        if isinstance(per_slot, np.ndarray):
            per_slot = link_columns(per_slot, serving, cols, slots)[0]
        elif moved:
            from caviar_plugins.torch_device import to_torch

            spread = per_slot.new_full((per_slot.shape[0], width, per_slot.shape[2]), float("nan"))
            spread[:, to_torch(cols, per_slot.device)] = per_slot
            per_slot = spread
        placed.append(per_slot)
    return link.run_links(placed, serving_cols, slots, backlogs)


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
