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

Pure numpy, one :class:`MobilityManager` for all UEs; times are virtual seconds.
"""

from __future__ import annotations

import dataclasses
from typing import Any


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


@dataclasses.dataclass
class _UeState:
    serving: int
    candidate: int = -1
    since: float = 0.0  # when the candidate started meeting A3
    below_since: float | None = None  # when the SINR fell below q_out
    filtered: list[float] | None = None  # layer-3 filtered RSRP per cell


class MobilityManager:
    """The serving cell of every UE, and the events that change it."""

    def __init__(self, settings: HandoverSettings, cell_names: list[str]):
        self.settings = settings
        self.cell_names = cell_names
        self.ues: dict[str, _UeState] = {}

    def serving(self, ue: str) -> int:
        """The cell index serving ``ue``; -1 when it is out of coverage."""
        st = self.ues.get(ue)
        return st.serving if st is not None else -1

    def forget(self, ue: str) -> None:
        self.ues.pop(ue, None)

    def update(self, t: float, ue: str, rsrp_dbm: list[float], sinr_db: float | None = None) -> list[dict[str, Any]]:
        """One measurement of UE ``ue`` at time ``t``: RSRP of every cell (dBm), and
        the SINR on its serving cell when known. Returns the events it caused
        (``attach``, ``handover``, ``rlf``, ``coverage_lost``), each ``{"event", "UE_Id",
        "time", …}``."""
        s = self.settings
        st = self.ues.get(ue)
        if st is not None and st.filtered is not None:
            a = 0.5 ** (s.l3_filter_k / 4)
            rsrp_dbm = [(1 - a) * f + a * m for f, m in zip(st.filtered, rsrp_dbm, strict=True)]
        best = max(range(len(rsrp_dbm)), key=lambda c: rsrp_dbm[c])
        if rsrp_dbm[best] < s.min_rsrp_dbm:
            if st is None:
                return []
            del self.ues[ue]
            ev = self._event("coverage_lost", ue, t, st.serving, best, rsrp_dbm)
            del ev["to_cell"], ev["rsrp_to_dbm"]
            return [ev]
        if st is None:
            self.ues[ue] = _UeState(serving=best, filtered=list(rsrp_dbm))
            return [self._event("attach", ue, t, None, best, rsrp_dbm)]
        st.filtered = list(rsrp_dbm)
        events: list[dict[str, Any]] = []
        # Radio-link failure: SINR below q_out for T310.
        if sinr_db is not None and sinr_db < s.q_out_db:
            if st.below_since is None:
                st.below_since = t
            elif t - st.below_since >= s.t310_s - 1e-9:
                old = st.serving
                self.ues[ue] = _UeState(serving=best, filtered=st.filtered)
                ev = self._event("rlf", ue, t, old, best, rsrp_dbm)
                ev["sinr_db"] = round(float(sinr_db), 3)
                return [ev]
        else:
            st.below_since = None
        ms = rsrp_dbm[st.serving]
        # The neighbours meeting A3's entering condition; the timer runs for the best
        # of them while it keeps meeting it, and starts again for another one.
        entering = [c for c in range(len(rsrp_dbm))
                    if c != st.serving and rsrp_dbm[c] - s.hysteresis_db > ms + s.offset_db]
        if not entering:
            st.candidate = -1
        else:
            top = max(entering, key=lambda c: rsrp_dbm[c])
            if st.candidate != top:
                st.candidate, st.since = top, t
        if st.candidate >= 0 and t - st.since >= s.time_to_trigger_s - 1e-9:
            old, new = st.serving, st.candidate
            self.ues[ue] = _UeState(serving=new, filtered=st.filtered)
            events.append(self._event("handover", ue, t, old, new, rsrp_dbm))
        return events

    def _event(self, kind: str, ue: str, t: float, old: int | None, new: int, rsrp: list[float]) -> dict[str, Any]:
        ev: dict[str, Any] = {"event": kind, "UE_Id": ue, "time": round(t, 9),
                              "to_cell": self.cell_names[new], "rsrp_to_dbm": round(float(rsrp[new]), 3)}
        if old is not None:
            ev["from_cell"] = self.cell_names[old]
            ev["rsrp_from_dbm"] = round(float(rsrp[old]), 3)
        return ev
