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
=================  ==========================================================================

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

from caviar_plugins.schema import MEASUREMENTS

FIELDS = ("time_s", "rx_x", "rx_y", "rx_z", "tx_x", "tx_y", "tx_z", "power_dbm", "tx_power_dbm",
          "frequency_hz", "bandwidth_hz")
"""The columns of the format, all required."""
TOPIC = MEASUREMENTS
"""Measurements travel on ``measurements.<vehicle>``: a payload is one sample (a mapping of
:data:`FIELDS`) or ``{"samples": [sample, …]}``."""
POSITIVE = ("frequency_hz", "bandwidth_hz")


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

    def __len__(self) -> int:
        return int(self.power_dbm.shape[0])

    def transmitters(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct transmitter positions (M × 3) and each sample's index among them."""
        sites, index = np.unique(np.round(self.tx, 6), axis=0, return_inverse=True)
        return sites, index.reshape(-1)

    def subset(self, mask: np.ndarray) -> Measurements:
        return Measurements(self.time_s[mask], self.rx[mask], self.tx[mask], self.power_dbm[mask],
                            self.tx_power_dbm[mask], self.frequency_hz, self.bandwidth_hz)

    @staticmethod
    def join(parts: list[Measurements]) -> Measurements:
        """Several sets of one carrier and bandwidth as one (a ValueError otherwise)."""
        if {(p.frequency_hz, p.bandwidth_hz) for p in parts} != {(parts[0].frequency_hz, parts[0].bandwidth_hz)}:
            raise MeasurementError("measurements of different carriers or bandwidths cannot be fitted together")
        def cat(field: str) -> np.ndarray:
            return np.concatenate([getattr(p, field) for p in parts])

        return Measurements(cat("time_s"), cat("rx"), cat("tx"), cat("power_dbm"), cat("tx_power_dbm"),
                            parts[0].frequency_hz, parts[0].bandwidth_hz)

    def rows(self) -> list[dict[str, float]]:
        """The samples as mappings of :data:`FIELDS` (what a topic carries)."""
        out = []
        for i in range(len(self)):
            out.append({"time_s": float(self.time_s[i]),
                        **{f"rx_{a}": float(self.rx[i, k]) for k, a in enumerate("xyz")},
                        **{f"tx_{a}": float(self.tx[i, k]) for k, a in enumerate("xyz")},
                        "power_dbm": float(self.power_dbm[i]), "tx_power_dbm": float(self.tx_power_dbm[i]),
                        "frequency_hz": self.frequency_hz, "bandwidth_hz": self.bandwidth_hz})
        return out

    def write_csv(self, path: str | pathlib.Path) -> pathlib.Path:
        path = pathlib.Path(path)
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(FIELDS))
            writer.writeheader()
            for row in self.rows():
                writer.writerow({k: repr(v) for k, v in row.items()})
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


def from_rows(rows: Iterable[tuple[str, Mapping[str, Any]]], source: str) -> Measurements:
    """Measurements from ``(where, row)`` pairs (``where`` names the row in errors, e.g.
    ``"m.csv row 3 (line 4)"``); ``source`` names them all (a file, a topic)."""
    values: list[list[float]] = []
    carrier: tuple[float, float, str] | None = None
    for where, row in rows:
        if not isinstance(row, Mapping):
            raise MeasurementError(f"{where}: expected a mapping of {', '.join(FIELDS)}, got {type(row).__name__}")
        missing = [f for f in FIELDS if f not in row or row[f] in ("", None)]
        if missing:
            raise MeasurementError(f"{where}: field '{missing[0]}' is missing (a sample has {', '.join(FIELDS)})")
        unknown = sorted(set(row) - set(FIELDS))
        if unknown:
            raise MeasurementError(f"{where}: unknown field '{unknown[0]}' (a sample has {', '.join(FIELDS)})")
        v = [_number(row[f], where, f) for f in FIELDS]
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
    return Measurements(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], a[:, 8], carrier[0], carrier[1])


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
            unknown = [c for c in reader.fieldnames or [] if c not in FIELDS]
            if unknown:
                raise MeasurementError(f"{path} line 1: unknown column '{unknown[0]}' (the columns are "
                                       f"{', '.join(FIELDS)})")
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
