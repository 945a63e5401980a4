"""What the view shows, read from a run directory and kept up to date while it grows.

A run that is still going leaves one Parquet part per recorded step, a finished run
one compacted file per table; :class:`caviar.rundir.RunDir` says which files hold a
table (the core knows the layout). :class:`RunData` remembers which it has read, and
:meth:`RunData.refresh` reads only files it has not seen (a directory listing is the
whole cost of a poll with nothing new).

Which topics are positions, link data, frames and events comes from the plugins'
:class:`~caviar.view.contract.ViewContract` (entry-point group ``caviar.view``): this
module names no domain topic.
"""

from __future__ import annotations

import bisect
import json
import math
import os
import pathlib
import threading
import time as _time
from typing import IO, Any

from caviar.rundir import RunDir, read_parquet
from caviar.view.contract import ViewContract, registered

VIEW_PREFIX = "view."

MSG_COLUMNS = ["step", "time", "source", "topic", "kind", "text", "meta"]


class RunDirError(Exception):
    """The run directory is missing, is not a run directory, or cannot be read."""


def _num(v):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _r(v, nd=3):
    return None if v is None else round(v, nd)


def _summary(payload, limit=160) -> str:
    if isinstance(payload, dict):
        parts = []
        for k, v in payload.items():
            if isinstance(v, (list, dict)):
                v = f"[{len(v)}]"
            elif isinstance(v, float):
                v = f"{v:.4g}"
            parts.append(f"{k}={v}")
        s = ", ".join(parts)
    else:
        s = json.dumps(payload)
    return s if len(s) <= limit else s[: limit - 1] + "…"


class RunData:
    """The view's data of one run, updated incrementally; thread-safe.

    ``pending=True`` accepts a directory that does not exist yet or has no
    ``run.json`` (``caviar-core run --view`` starts the server before the first step).
    """

    min_poll_s = 0.1
    """Polls closer together than this share one directory listing."""

    def __init__(self, run_dir: str | os.PathLike, pending: bool = False, contract: ViewContract | None = None):
        self.path = pathlib.Path(run_dir).absolute()
        self.run = RunDir(self.path)
        self.contract = registered() if contract is None else contract
        self.pending = pending
        self._lock = threading.RLock()
        self.status: dict = {}
        self._status_mtime: int | None = None
        self.config: dict = {}
        self._parts: dict[str, set[str]] = {"messages": set(), "timings": set()}
        self._merged = {"messages": False, "timings": False}
        self._bad_parts: dict[str, int] = {}
        self._msg_steps: set[int] = set()
        self._timing_steps: set[int] = set()
        self.step_time: dict[int, float] = {}
        self._sorted_steps: list[int] = []
        self.entities: dict[str, dict] = {}  # id -> {"type", "p": [[step, x, y, z], ...]}
        self.radio: dict[str, dict[int, list]] = {}  # ue -> step -> [thr, snr, los, pair]
        self.events: list[dict] = []
        self.view: list[dict] = []
        self.view_images: set[str] = set()  # every ``file`` an ``images`` entry of a view.* message names
        self.timings: dict[str, list] = {}  # module -> [[step, wall_ms], ...]
        self.frames: dict[str, dict[int, pathlib.Path]] = {}  # topic -> step -> file holding it
        self.topics: set[str] = set()
        self.version = 0
        self._last_poll = 0.0
        if not pending:
            self._check_dir()
        self.refresh(force=True, strict=not pending)

    # ---- reading -------------------------------------------------------------------

    def _check_dir(self):
        p = self.path
        if not p.exists():
            raise RunDirError(f"{p}: no such directory")
        if not p.is_dir():
            raise RunDirError(f"{p}: not a directory")
        try:
            self.run.require()
        except FileNotFoundError as e:
            raise RunDirError(str(e)) from None
        try:
            self.run.table_files("messages")
        except FileNotFoundError as e:
            raise RunDirError(str(e)) from None

    def _read_status(self, strict: bool):
        stamp = self.run.status_stamp()
        # A running run is read at every poll even when run.json did not change: a process
        # killed without closing it is seen as abandoned (the core's reading of its pid).
        if stamp is None or (stamp == self._status_mtime and self.status.get("status") != "running"):
            return
        try:
            status = self.run.status()  # (the core's reading: a run whose process died says so)
        except (OSError, ValueError) as e:
            if strict:
                raise RunDirError(f"{self.path}: unreadable run status ({e})") from None
            return  # being rewritten: next poll
        if status == self.status and stamp == self._status_mtime:
            return
        self.status, self._status_mtime = status, stamp
        self.version += 1
        if not self.config:
            try:
                self.config = self.run.config()
            except ValueError as e:
                if strict:
                    raise RunDirError(str(e)) from None

    @property
    def running(self) -> bool:
        return self.status.get("status") in (None, "running")

    def refresh(self, force: bool = False, strict: bool = False) -> bool:
        """Reads what is new; True if anything changed. Cheap to call often."""
        with self._lock:
            now = _time.monotonic()
            if not force and now - self._last_poll < (self.min_poll_s if self.running else 1.0):
                return False
            self._last_poll = now
            before = self.version
            self._read_status(strict)
            for table in ("messages", "timings"):
                self._read_table(table, strict)
            return self.version != before

    def _read_table(self, table: str, strict: bool):
        try:
            files = self.run.table_files(table)
        except FileNotFoundError:
            return  # nothing recorded yet
        columns = MSG_COLUMNS if table == "messages" else None
        if self.run.is_compacted(table, files):
            if self._merged[table]:
                return
            try:
                df = read_parquet(files[0], columns)
            except ValueError as e:
                if strict:
                    raise RunDirError(str(e)) from None
                return  # the recorder may still be writing it
            self._merged[table] = True
            self._ingest(table, df, files[0])
            return
        for f in files:
            if f.name in self._parts[table]:
                continue
            try:
                df = read_parquet(f, columns)
            except ValueError as e:
                tries = self._bad_parts[f.name] = self._bad_parts.get(f.name, 0) + 1
                if strict and not self.running:
                    raise RunDirError(str(e)) from None
                if tries < 20:
                    return  # perhaps still being written: parts are read in order, retry later
                continue
            self._parts[table].add(f.name)
            self._ingest(table, df, f)

    def _ingest(self, table: str, df, where: pathlib.Path):
        import polars as pl

        if df.is_empty():
            return
        seen = self._msg_steps if table == "messages" else self._timing_steps
        if seen:
            df = df.filter(~pl.col("step").is_in(list(seen)))
            if df.is_empty():
                return
        df = df.sort(["step", "seq"] if "seq" in df.columns else ["step"], maintain_order=True)
        steps = df.select("step", "time").unique("step")
        for s, t in steps.iter_rows():
            self.step_time.setdefault(int(s), float(t))
        seen.update(int(s) for s in steps["step"].to_list())
        if table == "timings":
            for step, module, wall in df.select("step", "module", "wall_s").iter_rows():
                self.timings.setdefault(module, []).append([int(step), _r(_num(wall) and wall * 1e3, 4)])
        else:
            self._ingest_messages(df, where)
        self._sorted_steps = sorted(self.step_time)
        self.version += 1

    def _ingest_messages(self, df, where: pathlib.Path):
        import polars as pl

        c = self.contract
        self.topics.update(df["topic"].unique().to_list())
        frames = df.filter(pl.col("kind") == "binary")
        for step, topic in frames.select("step", "topic").iter_rows():
            if c.is_frame(topic):
                self.frames.setdefault(topic, {})[int(step)] = where
        js = df.filter(pl.col("kind") == "json")
        interesting = pl.col("topic").is_in(list(c.positions + c.throughput + c.link + c.event_topics)) \
            | pl.col("topic").str.starts_with(VIEW_PREFIX)
        for prefix in c.event_prefixes:
            interesting = interesting | pl.col("topic").str.starts_with(prefix)
        for step, t, source, topic, text in js.filter(interesting).select(
                "step", "time", "source", "topic", "text").iter_rows():
            try:
                payload = json.loads(text)
            except (TypeError, ValueError):
                continue
            self._message(int(step), t, source, topic, payload)

    def _message(self, step: int, t: float, source: str, topic: str, payload: Any) -> None:
        """One decoded JSON message the view shows."""
        c = self.contract
        if topic in c.positions:
            for d in payload if isinstance(payload, list) else [payload]:
                self._position(step, d)
        elif topic in c.throughput or topic in c.link:
            self._radio(step, topic in c.throughput, payload)
        elif topic.startswith(VIEW_PREFIX):
            if isinstance(payload, dict):
                self.view.append({"step": step, "source": source, "topic": topic, "data": payload})
                images = payload.get("images")
                for im in images if isinstance(images, list) else []:
                    if isinstance(im, dict) and isinstance(im.get("file"), str):
                        self.view_images.add(im["file"])
        elif c.is_event(topic):
            for required_topic, field in c.event_requires:
                if topic == required_topic and isinstance(payload, dict) and not payload.get(field):
                    return  # e.g. detections with nothing found are not events
            ev = {"step": step, "time": t, "topic": topic, "source": source, "text": _summary(payload)}
            if isinstance(payload, dict) and _num(payload.get("x")) is not None and _num(payload.get("y")) is not None:
                ev["x"], ev["y"] = _num(payload["x"]), _num(payload["y"])
            self.events.append(ev)

    def _position(self, step: int, d):
        if not isinstance(d, dict):
            return
        ue = d.get("UE_Id", d.get("id"))
        pos = d.get("position")
        if ue is None or not isinstance(pos, dict):
            return
        x, y, z = (_num(pos.get(k)) for k in "xyz")
        if x is None or y is None:
            return
        e = self.entities.setdefault(str(ue), {"type": str(d.get("UE_type", "UE")), "p": []})
        pts = e["p"]
        row = [step, _r(x), _r(y), _r(z or 0.0)]
        if pts and pts[-1][0] == step:
            pts[-1] = row  # the latest of a step wins
        else:
            pts.append(row)

    def _radio(self, step: int, is_throughput: bool, d):
        if not isinstance(d, dict) or d.get("UE_Id") is None:
            return
        rec = self.radio.setdefault(str(d["UE_Id"]), {}).setdefault(step, [None, None, None, None])
        if is_throughput:
            rec[0] = _r(_num(d.get("throughput")), 4)
        else:
            rec[1] = _r(_num(d.get("snr_db")), 3)
            if isinstance(d.get("los"), bool):
                rec[2] = d["los"]
            pair = d.get("pair", d.get("beam_index"))
            rec[3] = int(pair) if isinstance(pair, int) and not isinstance(pair, bool) else None
            if rec[0] is None and _num(d.get("throughput")) is not None:
                rec[0] = _r(_num(d.get("throughput")), 4)

    # ---- queries -------------------------------------------------------------------

    @property
    def last_step(self) -> int | None:
        return self._sorted_steps[-1] if self._sorted_steps else None

    def status_summary(self) -> dict:
        s = self.status
        return {k: s.get(k) for k in ("status", "steps_done", "steps_planned", "error", "ts", "virtual_time_s")} | {
            "last_step": self.last_step, "waiting": not s}

    def next_steps(self) -> list[int]:
        """The first message step and the first timing step not read yet."""
        with self._lock:
            return [max(self._msg_steps, default=-1) + 1, max(self._timing_steps, default=-1) + 1]

    def since(self, step: int, tstep: int | None = None) -> dict:
        """Everything recorded at steps >= ``step`` (timings: >= ``tstep``, default
        ``step``), compact: what the page loads and what each live update pushes.
        ``next`` says where the next update starts (messages, timings)."""
        tstep = step if tstep is None else tstep
        with self._lock:
            lo = bisect.bisect_left(self._sorted_steps, step)
            ents = {}
            for k, e in self.entities.items():
                pts = e["p"]
                i = bisect.bisect_left(pts, [step])
                if i < len(pts):
                    ents[k] = {"type": e["type"], "p": pts[i:]}
            radio = {ue: [[s, *r] for s, r in sorted(recs.items()) if s >= step] for ue, recs in self.radio.items()}
            lo = min(lo, bisect.bisect_left(self._sorted_steps, tstep))
            return {
                "status": self.status_summary(),
                "since": [step, tstep],
                "next": self.next_steps(),
                "steps": [[s, self.step_time[s]] for s in self._sorted_steps[lo:]],
                "entities": ents,
                "radio": {k: v for k, v in radio.items() if v},
                "events": [e for e in self.events if e["step"] >= step],
                "view": [v for v in self.view if v["step"] >= step],
                "timings": {m: rows[bisect.bisect_left(rows, [tstep]):] for m, rows in self.timings.items()},
                "frames": {t: sorted(s for s in steps if s >= step) for t, steps in self.frames.items()},
            }

    def names_image(self, name: str) -> bool:
        """Whether an ``images`` entry of a recorded ``view.*`` message names the file ``name``
        (exactly as written there): the only run files the view serves as image layers."""
        with self._lock:
            return name in self.view_images

    def frame(self, topic: str, step: int):
        """The image on ``topic`` at the latest step <= ``step`` as (step, uint8 H×W×{1,3,4}),
        or None."""
        import numpy as np

        with self._lock:
            steps = self.frames.get(topic)
            if not steps:
                return None
            cands = [s for s in steps if s <= step]
            if not cands:
                return None
            s = max(cands)
            f = steps[s]
        df = self._frame_rows(topic, s, f)
        if df is None or df.is_empty():
            return None
        data, meta = df.row(-1)
        info = json.loads(meta) if meta else {}
        if "dtype" not in info or "shape" not in info:
            return None
        arr = np.frombuffer(data, dtype=np.dtype(info["dtype"])).reshape(info["shape"])
        if arr.ndim == 2:
            arr = arr[..., None]
        if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4):
            return None
        if arr.dtype != np.uint8:
            a = arr.astype(float)
            hi = a.max() if a.size and a.max() > 1.0 else 1.0
            arr = (np.clip(a / hi, 0, 1) * 255 + 0.5).astype(np.uint8)
        return s, arr

    frame_read_tries = 5
    """Listings of a frame's files before it is given up: a file can vanish between being
    listed and being opened (the recorder merged its parts, or compacted the finished run)."""

    def _frame_rows(self, topic: str, step: int, part: pathlib.Path):
        """The rows of ``topic`` at ``step`` (data, meta), read from the file that held
        them when indexed or, once that is gone, from the table's files as they are now.
        The files are opened first and read through their handles, so a file removed
        after that is still read whole; one removed between listing and opening is
        listed again. None when every try met a file that went away."""
        import contextlib

        import polars as pl

        for attempt in range(self.frame_read_tries):
            with contextlib.ExitStack() as stack:
                try:
                    where = [part] if part.is_file() else self.run.table_files("messages")
                    handles: list[IO[bytes]] = [stack.enter_context(open(f, "rb")) for f in where]
                except OSError:  # FileNotFoundError included: list again
                    _time.sleep(0.002 * (attempt + 1))
                    continue
                return pl.scan_parquet(handles).filter(
                    (pl.col("step") == step) & (pl.col("topic") == topic)).select("data", "meta").collect()
        return None


def png_bytes(arr) -> bytes:
    """A PNG of a uint8 H×W×C image (C = 1, 3 or 4), with the standard library's zlib."""
    import struct
    import zlib

    import numpy as np

    h, w, c = arr.shape
    colour = {1: 0, 3: 2, 4: 6}[c]
    raw = np.concatenate([np.zeros((h, 1), np.uint8), np.ascontiguousarray(arr).reshape(h, w * c)], axis=1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))
