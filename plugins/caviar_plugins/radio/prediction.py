"""Link predictions: where each UE will be at the horizons the user asks for, and what
its link will be there (the live twin's output to its physical twin).

At every step, for every UE and horizon h, the position at t + h comes from the UE's
forecast when its mobility module publishes one (``3D.mobility.forecast``: the planned
positions, one per forecast ``ts``) and reaches that far, and else from a
constant-velocity extrapolation: at the velocity the position payload reports (a
``velocity`` field, as mavlink-telemetry and sumo-traffic give), or else the one of its
last two positions (a live UE without a flight plan). ``sionna-link`` traces the
forecast positions in the same solve as the current ones (look-ahead ray tracing) and
publishes per UE on ``communications.prediction``::

    {"UE_type", "UE_Id", "time": t, "predictions": [
        {"horizon_s": h, "at_s": t + h, "source": "forecast" | "constant-velocity" | "hold",
         "position": {x, y, z}, "path_gain_db", "los", "best_pair", "best_throughput"}, …]}

Everything predicted is recorded, so a run's prediction error can be computed afterwards
against what happened (``communications.link`` at t + h):
:func:`prediction_errors`, drawn by ``caviar-core report``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from caviar_plugins.radio.link_report import db

SOURCES = ("forecast", "constant-velocity", "hold")


@dataclasses.dataclass
class Track:
    """What is known of one UE's motion: its last two positions and their times, and its
    forecast (positions every ``forecast_ts`` seconds after ``forecast_time``)."""

    position: np.ndarray
    time: float
    previous: tuple[np.ndarray, float] | None = None
    velocity: np.ndarray | None = None
    """The velocity the UE reported with its position (m/s), if it did."""
    forecast: list[np.ndarray] = dataclasses.field(default_factory=list)
    forecast_ts: float = 0.0
    forecast_time: float = 0.0


class Forecaster:
    """Positions of every UE at horizons after now; see the module documentation."""

    def __init__(self, horizons_s: Sequence[float]):
        self.horizons = [float(h) for h in horizons_s]
        self.tracks: dict[str, Track] = {}

    def observe(self, ue: str, t: float, position: np.ndarray, velocity: np.ndarray | None = None) -> None:
        """``position`` measured at ``t`` (a live UE's: the step's time less the sample's
        age), at ``velocity`` if the UE reported one."""
        track = self.tracks.get(ue)
        p = np.asarray(position, dtype=float)
        if track is None:
            track = self.tracks[ue] = Track(p, t)
        elif t > track.time:
            track.previous = (track.position, track.time)
            track.position, track.time = p, t
        else:
            track.position = p
        track.velocity = None if velocity is None else np.asarray(velocity, dtype=float)

    def plan(self, ue: str, t: float, positions: Iterable[np.ndarray], ts: float) -> None:
        """The UE's forecast published at ``t``: its positions at t + ts, t + 2·ts, …"""
        track = self.tracks.get(ue)
        if track is not None:
            track.forecast = [np.asarray(q, dtype=float) for q in positions]
            track.forecast_ts, track.forecast_time = float(ts), t

    def ahead(self, ue: str, t: float) -> list[tuple[float, str, np.ndarray]]:
        """(horizon, source, position) of ``ue`` at each horizon after ``t``."""
        track = self.tracks[ue]
        out = []
        for h in self.horizons:
            k = (t + h - track.forecast_time) / track.forecast_ts if track.forecast_ts > 0 else 0.0
            step = round(k)
            if track.forecast and abs(k - step) < 1e-6 and 1 <= step <= len(track.forecast):
                out.append((h, "forecast", track.forecast[step - 1]))
            elif track.velocity is not None or track.previous is not None:
                if track.velocity is not None:
                    v = track.velocity
                else:
                    (p0, t0) = track.previous  # type: ignore[misc]
                    v = (track.position - p0) / (track.time - t0)
                out.append((h, "constant-velocity", track.position + v * (t + h - track.time)))
            else:
                out.append((h, "hold", track.position))
        return out


def position_json(p: np.ndarray) -> dict[str, float]:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def prediction_payload(ue_type: str, ue: str, t: float, ahead: Sequence[tuple[float, str, np.ndarray]],
                       links: Sequence[Any], mbps) -> dict[str, Any]:
    """The ``communications.prediction`` payload of one UE: per horizon, the link a
    :class:`~caviar_plugins.radio.scene.Link` gives at the predicted position."""
    return {"UE_type": ue_type, "UE_Id": ue, "time": t, "predictions": [
        {"horizon_s": h, "at_s": round(t + h, 9), "source": source, "position": position_json(p),
         "path_gain_db": db(link.path_gain), "los": bool(link.los), "best_pair": link.best_pair,
         "best_throughput": mbps(float(link.gains.max()))}
        for (h, source, p), link in zip(ahead, links, strict=True)]}


def prediction_errors(predictions: Iterable[Mapping[str, Any]],
                      realised: Iterable[tuple[float, Mapping[str, Any]]],
                      tolerance_s: float = 1e-6) -> dict[float, dict[str, Any]]:
    """Per horizon, the predictions (payloads of ``communications.prediction``) against
    what happened (``(time, payload)`` of ``communications.link``): the path gain error
    in dB (mean, mean absolute, p95 absolute), the share with the same best pair, and the
    line-of-sight transitions (a change of LOS between the prediction's time and t + h)
    that were predicted. Each horizon also lists its (predicted, realised) path gains."""
    actual: dict[tuple[str, int], Mapping[str, Any]] = {}
    for time, m in realised:
        actual[(m["UE_Id"], round(time / tolerance_s))] = m
    rows: dict[float, list[tuple[float, float, bool, bool, bool]]] = {}
    for m in predictions:
        now = actual.get((m["UE_Id"], round(m["time"] / tolerance_s)))
        for p in m["predictions"]:
            then = actual.get((m["UE_Id"], round(p["at_s"] / tolerance_s)))
            if then is None or now is None:
                continue
            transition = bool(then["los"]) != bool(now["los"])
            rows.setdefault(p["horizon_s"], []).append(
                (p["path_gain_db"], then["path_gain_db"], p["best_pair"] == then["best_pair"], transition,
                 transition and bool(p["los"]) == bool(then["los"])))
    out = {}
    for h, r in sorted(rows.items()):
        pred, real = np.array([x[0] for x in r]), np.array([x[1] for x in r])
        err = pred - real
        transitions = sum(x[3] for x in r)
        out[h] = {"n": len(r), "path_gain_error_db": {
            "mean": float(err.mean()), "mean_abs": float(np.abs(err).mean()),
            "p95_abs": float(np.percentile(np.abs(err), 95))},
            "same_best_pair": float(np.mean([x[2] for x in r])),
            "los_transitions": transitions, "los_transitions_caught": int(sum(x[4] for x in r)),
            "pairs": [[float(a), float(b)] for a, b in zip(pred, real, strict=True)]}
    return out


def figures(log, out) -> list:
    """``caviar-core report`` (entry-point group ``caviar.report``): predicted against
    realised path gain per horizon, and the error by horizon (``prediction.png``), with
    the numbers in ``prediction.json``. Nothing for a run without predictions."""
    import json
    import pathlib

    from caviar_plugins.schema import LINK, PREDICTION

    predictions = [m.data for m in log.decoded(PREDICTION)]
    if not predictions:
        return []
    errors = prediction_errors(predictions, [(m.time, m.data) for m in log.decoded(LINK)])
    if not errors:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = pathlib.Path(out)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for h, e in errors.items():
        pairs = np.array(e["pairs"])
        axes[0].scatter(pairs[:, 1], pairs[:, 0], s=8, label=f"{h:g} s ({e['n']})")
    lo, hi = axes[0].get_xlim()
    axes[0].plot([lo, hi], [lo, hi], "k--", lw=0.8)
    axes[0].set(xlabel="realised path gain (dB)", ylabel="predicted path gain (dB)",
                title="predicted against what happened")
    axes[0].legend(title="horizon")
    hs = list(errors)
    axes[1].plot(hs, [errors[h]["path_gain_error_db"]["mean_abs"] for h in hs], "o-", label="mean |error|")
    axes[1].plot(hs, [errors[h]["path_gain_error_db"]["p95_abs"] for h in hs], "s--", label="p95 |error|")
    axes[1].set(xlabel="horizon (s)", ylabel="path gain error (dB)", title="error by horizon")
    axes[1].grid(True)
    axes[1].legend()
    fig.tight_layout()
    png = out / "prediction.png"
    fig.savefig(png, dpi=100)
    plt.close(fig)
    numbers = out / "prediction.json"
    numbers.write_text(json.dumps({str(h): {k: v for k, v in e.items() if k != "pairs"}
                                   for h, e in errors.items()}, indent=2) + "\n")
    return [png, numbers]
