"""Measurements of the radio environment, as data: the format a drive test, a flight or a
live vehicle reports in, and its readers (a CSV or Parquet file, messages on
``measurements.*``).

One sample per row (a CSV file's header names the columns; the order is free):

=================  ==========================================================================
column             meaning
=================  ==========================================================================
``time_s``         when it was measured (s, any origin)
``rx_x, rx_y,      the receiver's position in the scene's frame (m; x east, y north, z up for
rx_z``             a scene from ``caviar-core scene build``)
``tx_x, tx_y,      the transmitter's position (m)
tx_z``
``power_dbm``      the received power (dBm): the local average over the bandwidth, or over a
                   few wavelengths of track (what a scanner's RSRP × subcarriers, or a
                   power meter, reports)
``tx_power_dbm``   the transmitted power (dBm) into an isotropic antenna (EIRP)
``frequency_hz``   the carrier (Hz); one carrier per file
``bandwidth_hz``   the measured bandwidth (Hz)
``pdp_delay_s``,    optional, together: the power-delay profile, as taps: each tap's delay (s,
``pdp_power_dbm``  >= 0 from any origin: only differences count) and power (dBm); a CSV cell holds the
                   taps separated by ``;``, a Parquet column a list or such a string, a topic
                   a list. A sample without them has no profile (empty cells)
=================  ==========================================================================

A profile is read as its RMS delay spread, with the taps binned at the bandwidth's resolution
(1/``bandwidth_hz``) as a channel sounder's are (:func:`rms_delay_spread`): the fit predicts
the same from the traced paths and reports its error before and after, on the fit and the
held-out samples: a check of the multipath the fit never descended on.

Antennas are single elements (isotropic unless a fit says otherwise), vertically polarised.
Every value must be a finite number; a bad row gets a :class:`MeasurementError` naming the
file, the row (and its line) and the field.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import pathlib
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from caviar_plugins.rt.received_power import rms_delay_spread
from caviar_plugins.schema import MEASUREMENTS

FIELDS = ("time_s", "rx_x", "rx_y", "rx_z", "tx_x", "tx_y", "tx_z", "power_dbm", "tx_power_dbm",
          "frequency_hz", "bandwidth_hz")
"""The columns of the format every sample has."""
PDP_FIELDS = ("pdp_delay_s", "pdp_power_dbm")
"""The optional columns of a sample's power-delay profile (both or neither)."""
TOPIC = MEASUREMENTS
"""Measurements travel on ``measurements.<vehicle>``: a payload is one sample (a mapping of
:data:`FIELDS`) or ``{"samples": [sample, …]}``."""
POSITIVE = ("frequency_hz", "bandwidth_hz")
__all__ = ["FIELDS", "PDP_FIELDS", "TOPIC", "MeasurementError", "Measurements", "from_messages", "from_rows",
           "read_measurements", "rms_delay_spread"]


class MeasurementError(ValueError):
    """A measurement that cannot be used: names where (file and row, or topic and step) and
    the field."""


@dataclasses.dataclass
class Measurements:
    """Samples as arrays (see the module's table for the fields)."""

    time_s: np.ndarray
    rx: np.ndarray
    """Receiver positions, N × 3 (m)."""
    tx: np.ndarray
    """Transmitter positions, N × 3 (m)."""
    power_dbm: np.ndarray
    tx_power_dbm: np.ndarray
    frequency_hz: float
    bandwidth_hz: float
    pdp: list[tuple[np.ndarray, np.ndarray] | None] | None = None
    """Per sample, its power-delay profile's taps ``(delays_s, powers_dbm)``, or None (None:
    no sample has one)."""

    def __post_init__(self):
        if self.pdp is not None and len(self.pdp) != len(self):
            raise MeasurementError(f"pdp: {len(self.pdp)} profiles for {len(self)} samples (one per sample, None "
                                   "for a sample without one)")

    def __len__(self) -> int:
        return int(self.power_dbm.shape[0])

    def delay_spread_s(self) -> np.ndarray:
        """Each sample's RMS delay spread (s) from its profile (:func:`rms_delay_spread` at
        the bandwidth's resolution); NaN for a sample without one."""
        out = np.full(len(self), np.nan)
        for i, taps in enumerate(self.pdp or []):
            if taps is not None:
                out[i] = rms_delay_spread(taps[0], 10.0 ** (taps[1] / 10.0), 1.0 / self.bandwidth_hz)
        return out

    def transmitters(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct transmitter positions (M × 3) and each sample's index among them."""
        sites, index = np.unique(np.round(self.tx, 6), axis=0, return_inverse=True)
        return sites, index.reshape(-1)

    def subset(self, mask: np.ndarray) -> Measurements:
        """The samples where the boolean ``mask`` is true."""
        mask = np.asarray(mask, dtype=bool)
        pdp = None if self.pdp is None else [self.pdp[i] for i in np.flatnonzero(mask)]
        return Measurements(self.time_s[mask], self.rx[mask], self.tx[mask], self.power_dbm[mask],
                            self.tx_power_dbm[mask], self.frequency_hz, self.bandwidth_hz, pdp)

    @staticmethod
    def join(parts: list[Measurements]) -> Measurements:
        """Several sets of one carrier and bandwidth as one (a ValueError otherwise)."""
        if {(p.frequency_hz, p.bandwidth_hz) for p in parts} != {(parts[0].frequency_hz, parts[0].bandwidth_hz)}:
            raise MeasurementError("measurements of different carriers or bandwidths cannot be fitted together")
        def cat(field: str) -> np.ndarray:
            return np.concatenate([getattr(p, field) for p in parts])

        pdp = None
        if any(p.pdp is not None for p in parts):
            pdp = [taps for p in parts for taps in (p.pdp if p.pdp is not None else [None] * len(p))]
        return Measurements(cat("time_s"), cat("rx"), cat("tx"), cat("power_dbm"), cat("tx_power_dbm"),
                            parts[0].frequency_hz, parts[0].bandwidth_hz, pdp)

    def rows(self) -> list[dict[str, Any]]:
        """The samples as mappings of :data:`FIELDS` and, for a sample with a profile, of
        :data:`PDP_FIELDS` as lists (what a topic carries)."""
        out: list[dict[str, Any]] = []
        for i in range(len(self)):
            out.append({"time_s": float(self.time_s[i]),
                        **{f"rx_{a}": float(self.rx[i, k]) for k, a in enumerate("xyz")},
                        **{f"tx_{a}": float(self.tx[i, k]) for k, a in enumerate("xyz")},
                        "power_dbm": float(self.power_dbm[i]), "tx_power_dbm": float(self.tx_power_dbm[i]),
                        "frequency_hz": self.frequency_hz, "bandwidth_hz": self.bandwidth_hz})
            taps = self.pdp[i] if self.pdp is not None else None
            if taps is not None:
                out[-1].update(pdp_delay_s=[float(v) for v in taps[0]], pdp_power_dbm=[float(v) for v in taps[1]])
        return out

    def write_csv(self, path: str | pathlib.Path) -> pathlib.Path:
        """The samples as a CSV file (the profile's columns where a sample has one)."""
        path = pathlib.Path(path)
        fields = [*FIELDS, *(PDP_FIELDS if self.pdp is not None else ())]
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields, restval="")
            writer.writeheader()
            for row in self.rows():
                writer.writerow({k: ";".join(map(repr, v)) if isinstance(v, list) else repr(v) for k, v in row.items()})
        return path


def _number(value: Any, where: str, field: str) -> float:
    if isinstance(value, bool):
        raise MeasurementError(f"{where}: field '{field}': expected a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise MeasurementError(f"{where}: field '{field}': expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise MeasurementError(f"{where}: field '{field}': expected a finite number, got {value!r}")
    if field in POSITIVE and x <= 0:
        raise MeasurementError(f"{where}: field '{field}': expected a number > 0 (Hz), got {value!r}")
    return x


def _numbers(value: Any, where: str, field: str) -> np.ndarray:
    """A profile's column: a list of numbers, or a string of them separated by ``;``."""
    if isinstance(value, str):
        items: list[Any] = [v for v in value.split(";") if v.strip()]
    elif isinstance(value, (list, tuple, np.ndarray)):
        items = list(value)
    else:
        raise MeasurementError(f"{where}: field '{field}': expected a list of numbers (or a string of them "
                               f"separated by ';'), got {value!r}")
    if not items:
        raise MeasurementError(f"{where}: field '{field}': expected at least one tap, got none")
    out = np.array([_number(v, f"{where} tap {k}", field) for k, v in enumerate(items)], dtype=np.float64)
    if field == "pdp_delay_s" and (out < 0).any():
        k = int(np.flatnonzero(out < 0)[0])
        raise MeasurementError(f"{where} tap {k}: field '{field}': expected delays >= 0 (s), got {out[k]!r}")
    return out


def _empty(value: Any) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def _profile(row: Mapping[str, Any], where: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A sample's power-delay profile (:data:`PDP_FIELDS`), None where its cells are empty."""
    given = [f for f in PDP_FIELDS if not _empty(row.get(f))]
    if not given:
        return None
    if len(given) == 1:
        other = PDP_FIELDS[1 - PDP_FIELDS.index(given[0])]
        raise MeasurementError(f"{where}: field '{other}' is missing (a profile has both {' and '.join(PDP_FIELDS)})")
    delays, powers = (_numbers(row[f], where, f) for f in PDP_FIELDS)
    if len(delays) != len(powers):
        raise MeasurementError(f"{where}: field 'pdp_power_dbm': {len(powers)} taps, but 'pdp_delay_s' has "
                               f"{len(delays)} (one power per delay)")
    return delays, powers


def from_rows(rows: Iterable[tuple[str, Mapping[str, Any]]], source: str) -> Measurements:
    """Measurements from ``(where, row)`` pairs (``where`` names the row in errors, e.g.
    ``"m.csv row 3 (line 4)"``); ``source`` names them all (a file, a topic)."""
    values: list[list[float]] = []
    profiles: list[tuple[np.ndarray, np.ndarray] | None] = []
    carrier: tuple[float, float, str] | None = None
    for where, row in rows:
        if not isinstance(row, Mapping):
            raise MeasurementError(f"{where}: expected a mapping of {', '.join(FIELDS)}, got {type(row).__name__}")
        missing = [f for f in FIELDS if f not in row or row[f] in ("", None)]
        if missing:
            raise MeasurementError(f"{where}: field '{missing[0]}' is missing (a sample has {', '.join(FIELDS)})")
        unknown = sorted(set(row) - set(FIELDS) - set(PDP_FIELDS))
        if unknown:
            raise MeasurementError(f"{where}: unknown field '{unknown[0]}' (a sample has {', '.join(FIELDS)}, "
                                   f"and optionally {' and '.join(PDP_FIELDS)})")
        v = [_number(row[f], where, f) for f in FIELDS]
        profiles.append(_profile(row, where))
        f_hz, b_hz = v[FIELDS.index("frequency_hz")], v[FIELDS.index("bandwidth_hz")]
        if carrier is None:
            carrier = (f_hz, b_hz, where)
        elif (f_hz, b_hz) != carrier[:2]:
            field = "frequency_hz" if f_hz != carrier[0] else "bandwidth_hz"
            raise MeasurementError(f"{where}: field '{field}': {v[FIELDS.index(field)]:g} differs from "
                                   f"{carrier[2]}'s {carrier[0 if field == 'frequency_hz' else 1]:g} "
                                   "(one carrier and bandwidth per set of measurements)")
        values.append(v)
    if carrier is None:
        raise MeasurementError(f"{source}: no measurements")
    a = np.asarray(values, dtype=np.float64)
    pdp = profiles if any(p is not None for p in profiles) else None
    return Measurements(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], a[:, 8], carrier[0], carrier[1], pdp)


def read_measurements(path: str | pathlib.Path) -> Measurements:
    """Measurements from a CSV file (a header row names the columns) or a Parquet file."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise MeasurementError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    if path.suffix.lower() == ".parquet":
        import pyarrow.parquet as pq

        try:
            table = pq.read_table(path).to_pylist()
        except Exception as e:  # pyarrow raises several kinds for a file that is not Parquet
            raise MeasurementError(f"{path}: not a Parquet file ({e})") from None
        return from_rows(((f"{path} row {i + 1}", row) for i, row in enumerate(table)), str(path))
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            unknown = [c for c in reader.fieldnames or [] if c not in FIELDS and c not in PDP_FIELDS]
            if unknown:
                raise MeasurementError(f"{path} line 1: unknown column '{unknown[0]}' (the columns are "
                                       f"{', '.join(FIELDS)}, and optionally {' and '.join(PDP_FIELDS)})")
            rows = [(f"{path} row {i + 1} (line {reader.line_num})", dict(row)) for i, row in enumerate(reader)]
    except (UnicodeDecodeError, csv.Error) as e:
        raise MeasurementError(f"{path}: not a CSV file ({e})") from None
    for where, row in rows:
        if None in row:
            raise MeasurementError(f"{where}: more values than the header's {len(row) - 1} columns")
    return from_rows(rows, str(path))


def from_messages(messages: Iterable[Any]) -> Measurements:
    """Measurements from messages on ``measurements.*`` (:data:`TOPIC`)."""
    rows: list[tuple[str, Any]] = []
    for m in messages:
        where = f"topic {m.topic}" + (f" (step {m.step})" if getattr(m, "step", None) is not None else "")
        data = m.data
        if isinstance(data, Mapping) and "samples" in data:
            if not isinstance(data["samples"], list):
                raise MeasurementError(f"{where}: field 'samples': expected a list of samples")
            rows += [(f"{where} sample {i}", s) for i, s in enumerate(data["samples"])]
        else:
            rows.append((where, data))
    return from_rows(rows, "measurements.*")
