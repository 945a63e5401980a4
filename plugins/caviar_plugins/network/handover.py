"""Mobility management: handover on the 3GPP A3 event and radio-link failure.

**A3** (TS 38.331 §5.5.4.4): a neighbour becomes offset better than the serving cell,
``Mn − Hys > Ms + Off`` (RSRP, dB). When the condition holds for a whole
time-to-trigger the UE hands over to that neighbour. The condition must hold for the
*same* neighbour throughout; a neighbour that stops meeting it stops the timer. After
a handover the old cell must in turn be ``Off + Hys`` better than the new one, so with
``Off + Hys > 0`` and a time-to-trigger a UE on a cell border does not hand back and
forth (ping-pong) on measurement noise; with both 0 it does.

Measurements are layer-3 filtered first (TS 38.331 §5.5.3.2): ``F = (1 − a)·F + a·M``
with ``a = 1/2^(k/4)`` and ``k = l3_filter_k`` (4 by default; 0 turns the filter off).

**Radio-link failure** (TS 38.331 §5.3.10, simplified): while the serving cell's SINR
stays below ``q_out_db`` for ``t310_s`` the link is declared failed; the UE re-attaches
to the strongest cell (an event on its own topic), as after re-establishment.

Pure numpy, one :class:`MobilityManager` for all UEs, their state in arrays and one vectorised
update a step for all of them; times are virtual seconds.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class HandoverSettings:
    offset_db: float = 3.0
    hysteresis_db: float = 1.0
    time_to_trigger_s: float = 0.16
    q_out_db: float = -8.0
    t310_s: float = 1.0
    l3_filter_k: float = 4.0
    min_rsrp_dbm: float = -130.0
    """Cell selection (TS 38.304 S-criterion, Qrxlevmin): a UE whose best RSRP is below it
    is out of coverage, attached to no cell."""

    def __post_init__(self):
        for key in ("hysteresis_db", "time_to_trigger_s", "t310_s", "l3_filter_k"):
            v = getattr(self, key)
            if not v >= 0:
                raise ValueError(f"{key}: expected a number >= 0, got {v}")


class MobilityManager:
    """The serving cell of every UE, and the events that change it: the state of all UEs in
    arrays, one row a UE, and one vectorised update for all of them (:meth:`update_rows`).

    The radio network keys UEs by their link-level columns (rows); :meth:`update`,
    :meth:`serving` and :meth:`forget` take a UE's name instead, for one UE at a time."""

    def __init__(self, settings: HandoverSettings, cell_names: list[str]):
        self.settings = settings
        self.cell_names = cell_names
        self.rows: dict[str, int] = {}  # (the per-name API's UEs)
        # Per row: the serving cell (-1: none), the A3 candidate (-1: none) and since when it
        # meets A3, since when the SINR is below q_out (NaN: it is not), the filtered RSRP [cell].
        self.serving_cell = np.zeros(0, dtype=np.int64)
        self.candidate = np.zeros(0, dtype=np.int64)
        self.since, self.below_since = np.zeros(0), np.zeros(0)
        self.filtered = np.zeros((0, len(cell_names)))
        self._grow(0)

    def ensure(self, n: int) -> None:
        """Rows for ``n`` UEs at least (kept, the new ones unattached)."""
        self._grow(n)

    def _grow(self, n: int) -> None:
        k = len(self.serving_cell)
        if k and n <= k:
            return
        cap, c = max(n, 2 * k, 8), len(self.cell_names)
        grown = {"serving_cell": np.full(cap, -1, dtype=np.int64), "candidate": np.full(cap, -1, dtype=np.int64),
                 "since": np.zeros(cap), "below_since": np.full(cap, np.nan), "filtered": np.zeros((cap, c))}
        for name, a in grown.items():
            if k:
                a[:k] = getattr(self, name)
            setattr(self, name, a)

    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name).copy() for name in STATE} | {"rows": dict(self.rows)}

    def restore(self, state: dict[str, Any]) -> None:
        for name in STATE:
            setattr(self, name, state[name].copy())
        self.rows = dict(state["rows"])

    def serving(self, ue: str) -> int:
        """The cell index serving ``ue``; -1 when it is out of coverage."""
        row = self.rows.get(ue)
        return -1 if row is None else int(self.serving_cell[row])

    def forget(self, ue: str) -> None:
        row = self.rows.get(ue)
        if row is not None:
            self.forget_row(row)

    def forget_row(self, row: int) -> None:
        """Row ``row`` has no UE (yet): it starts unattached."""
        if row < len(self.serving_cell):
            self.serving_cell[row], self.candidate[row], self.since[row] = -1, -1, 0.0
            self.below_since[row] = np.nan

    def update(self, t: float, ue: str, rsrp_dbm: list[float], sinr_db: float | None = None) -> list[dict[str, Any]]:
        """One measurement of UE ``ue`` at time ``t``: RSRP of every cell (dBm), and
        the SINR on its serving cell when known. Returns the events it caused
        (``attach``, ``handover``, ``rlf``, ``coverage_lost``), each ``{"event", "UE_Id",
        "time", …}``."""
        row = self.rows.setdefault(ue, len(self.rows))
        return self.update_rows(t, np.array([row]), [ue], np.array([rsrp_dbm], dtype=float),
                                np.array([np.nan if sinr_db is None else sinr_db]))

    def update_rows(self, t: float, rows: np.ndarray, ids: list[str], rsrp_dbm: np.ndarray,
                    sinr_db: np.ndarray) -> list[dict[str, Any]]:
        """One measurement of the UEs in ``rows`` (distinct; named ``ids`` in the events) at
        time ``t``, all at once: RSRP [ue, cell] dBm and the SINR on the serving cell [ue]
        (NaN: not known). Returns the events, in the order of ``rows`` (at most one a UE)."""
        s = self.settings
        rows = np.asarray(rows, dtype=np.int64)
        self._grow(int(rows.max()) + 1 if len(rows) else 0)
        n, n_cell = rsrp_dbm.shape
        i = np.arange(n)
        serving = self.serving_cell[rows]
        had = serving >= 0
        m = np.asarray(rsrp_dbm, dtype=float)
        if had.any():  # (layer-3 filtered, those with a cell; the others' rows hold nothing)
            a = 0.5 ** (s.l3_filter_k / 4)
            with np.errstate(invalid="ignore"):
                m = np.where(had[:, None], (1 - a) * self.filtered[rows] + a * m, m)
        best = np.argmax(m, axis=1)
        lost = m[i, best] < s.min_rsrp_dbm
        attach = ~had & ~lost
        kept = had & ~lost
        # Radio-link failure: SINR below q_out for T310 (NaN: not below).
        below = kept & (np.asarray(sinr_db, dtype=float) < s.q_out_db)
        since_below = self.below_since[rows]
        rlf = below & ~np.isnan(since_below) & (t - since_below >= s.t310_s - 1e-9)
        since_below = np.where(below, np.where(np.isnan(since_below), t, since_below), np.nan)
        # A3: the neighbours meeting the entering condition; the timer runs for the best of
        # them while it keeps meeting it, and starts again for another one.
        sv = np.maximum(serving, 0)
        entering = ((m - s.hysteresis_db > (m[i, sv] + s.offset_db)[:, None])
                    & (np.arange(n_cell)[None, :] != sv[:, None]))
        top = np.where(entering.any(axis=1), np.argmax(np.where(entering, m, -np.inf), axis=1), -1)
        candidate, since = self.candidate[rows], self.since[rows]
        since = np.where((top >= 0) & (candidate != top), t, since)
        candidate = top
        handover = kept & ~rlf & (candidate >= 0) & (t - since >= s.time_to_trigger_s - 1e-9)
        fresh = attach | rlf | handover  # (a new serving cell: the timers start again)
        new = np.where(handover, candidate, np.where(attach | rlf, best, np.where(lost, -1, serving)))
        self.serving_cell[rows] = new
        self.candidate[rows] = np.where(fresh | lost, -1, candidate)
        self.since[rows] = np.where(fresh | lost, 0.0, since)
        self.below_since[rows] = np.where(fresh | lost, np.nan, since_below)
        self.filtered[rows] = np.where(lost[:, None], self.filtered[rows], m)
        events: list[dict[str, Any]] = []
        for k in np.flatnonzero(fresh | (had & lost)).tolist():
            if attach[k]:
                events.append(self._event("attach", ids[k], t, None, int(best[k]), m[k]))
            elif lost[k]:
                ev = self._event("coverage_lost", ids[k], t, int(serving[k]), int(best[k]), m[k])
                del ev["to_cell"], ev["rsrp_to_dbm"]
                events.append(ev)
            elif rlf[k]:
                ev = self._event("rlf", ids[k], t, int(serving[k]), int(best[k]), m[k])
                ev["sinr_db"] = round(float(sinr_db[k]), 3)
                events.append(ev)
            else:
                events.append(self._event("handover", ids[k], t, int(serving[k]), int(new[k]), m[k]))
        return events

    def _event(self, kind: str, ue: str, t: float, old: int | None, new: int, rsrp: np.ndarray) -> dict[str, Any]:
        ev: dict[str, Any] = {"event": kind, "UE_Id": ue, "time": round(t, 9),
                              "to_cell": self.cell_names[new], "rsrp_to_dbm": round(float(rsrp[new]), 3)}
        if old is not None:
            ev["from_cell"] = self.cell_names[old]
            ev["rsrp_from_dbm"] = round(float(rsrp[old]), 3)
        return ev


STATE = ("serving_cell", "candidate", "since", "below_since", "filtered")
"""The arrays of a :class:`MobilityManager`'s state, one row a UE."""
