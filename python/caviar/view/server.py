"""The view's HTTP server: read-only (GET and HEAD), standard library only.

It serves its own static files (by exact name), the run's data as JSON, live updates
as server-sent events, camera frames as PNG, files under the run directory (resolved,
symbolic links included, and refused if they land outside it), and the scene meshes
the run's scene XML references (by index into that allow-list, never by path).
"""

from __future__ import annotations

import json
import os
import pathlib
import posixpath
import sys
import threading
import time
import urllib.parse
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from caviar.view.data import RunData, png_bytes
from caviar.view.scene import find_scene, scene_meshes, transmitter

STATIC = pathlib.Path(__file__).parent / "static"
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
         ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8", ".json": "application/json",
         ".png": "image/png", ".jpg": "image/jpeg", ".csv": "text/csv; charset=utf-8", ".ply": "application/octet-stream",
         ".toml": "text/plain; charset=utf-8", ".svg": "image/svg+xml"}
CSP = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
       "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1", "[::1]"}


class ViewState:
    """What the handlers share: the run's data, its scene and the allow-lists."""

    def __init__(self, run_dir, pending: bool = False):
        self.data = RunData(run_dir, pending=pending)
        self.static = {p.name: p for p in STATIC.iterdir() if p.is_file() and not p.is_symlink()} if STATIC.is_dir() else {}
        self.stopping = threading.Event()
        self._scene = None
        self._scene_lock = threading.Lock()

    @property
    def run_dir(self) -> pathlib.Path:
        return self.data.path.resolve()

    def scene(self) -> dict:
        with self._scene_lock:
            if self._scene is None or (not self._scene["had_config"] and self.data.config):
                cfg = self.data.config
                cf = self.data.status.get("config_file")
                config_dir = pathlib.Path(cf).parent if isinstance(cf, str) and cf else None
                name, xml, origin = find_scene(cfg, config_dir, self.data.path)
                meshes = []
                if xml is not None:
                    try:
                        meshes = scene_meshes(xml)
                    except Exception as e:  # noqa: BLE001 - a bad scene must not stop the view
                        origin += f"; unreadable scene XML: {e}"
                self._scene = {"name": name, "xml": str(xml) if xml else None, "origin": origin, "meshes": meshes,
                               "tx": transmitter(cfg), "had_config": bool(cfg)}
            return self._scene

    def run_info(self) -> dict:
        sc = self.scene()
        cfg = self.data.config
        mods = cfg.get("modules", {}) if isinstance(cfg.get("modules"), dict) else {}
        return {
            "run_dir": str(self.data.path),
            "name": self.data.path.name,
            "status": self.data.status_summary(),
            "config_file": self.data.status.get("config_file"),
            "modules": [{"name": k, "plugin": v.get("plugin"), "stage": v.get("stage")}
                        for k, v in mods.items() if isinstance(v, dict)],
            "topics": sorted(self.data.topics),
            "scene": {"name": sc["name"], "xml": sc["xml"], "origin": sc["origin"],
                      "meshes": [{"url": f"/mesh/{i}", "id": m["id"], "material": m["material"], "matrix": m["matrix"]}
                                 for i, m in enumerate(sc["meshes"])]},
            "tx": sc["tx"],
        }


class Handler(BaseHTTPRequestHandler):
    server_version = "caviar-view"
    sys_version = ""
    protocol_version = "HTTP/1.1"
    state: ViewState  # set on the subclass made per server

    def log_message(self, fmt, *args):  # quiet: the page polls nothing but SSE keeps it busy
        if os.environ.get("CAVIAR_VIEW_LOG"):
            sys.stderr.write("view: " + fmt % args + "\n")

    # ---- methods -----------------------------------------------------------------------

    def _refuse_method(self):
        self._send(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only: GET and HEAD only\n", "text/plain; charset=utf-8",
                   extra={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_CONNECT = do_TRACE = _refuse_method

    def do_HEAD(self):
        self._get(head=True)

    def do_GET(self):
        self._get(head=False)

    # ---- responses ----------------------------------------------------------------------

    def _send(self, code, body: bytes, ctype: str, head: bool = False, extra: dict | None = None, cache: bool = False):
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", CSP)
        self.send_header("Referrer-Policy", "no-referrer")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if not head:
            self.wfile.write(body)

    def _error(self, code, msg, head):
        self._send(code, (msg + "\n").encode(), "text/plain; charset=utf-8", head)

    def _json(self, obj, head):
        self._send(HTTPStatus.OK, json.dumps(obj, separators=(",", ":"), allow_nan=False).encode(),
                   "application/json", head)

    def _file(self, path: pathlib.Path, head, cache=False):
        try:
            body = path.read_bytes()
        except OSError:
            return self._error(HTTPStatus.NOT_FOUND, "not found", head)
        self._send(HTTPStatus.OK, body, TYPES.get(path.suffix.lower(), "application/octet-stream"), head, cache=cache)

    # ---- routing ------------------------------------------------------------------------

    def _get(self, head: bool):
        st = self.state
        try:
            host = urllib.parse.urlsplit("//" + (self.headers.get("Host") or "")).hostname or ""
        except ValueError:
            host = ""
        if self.server.local_only and host not in LOCAL_HOSTS:  # DNS rebinding
            return self._error(HTTPStatus.FORBIDDEN, "forbidden host", head)
        url = urllib.parse.urlsplit(self.path)
        raw = url.path
        path = urllib.parse.unquote(raw)
        if "\x00" in path or "\\" in path or not path.startswith("/"):
            return self._error(HTTPStatus.BAD_REQUEST, "bad path", head)
        parts = path.split("/")[1:]
        if any(p in ("..", ".") for p in parts) or "//" in path:
            return self._error(HTTPStatus.FORBIDDEN, "forbidden path", head)
        q = urllib.parse.parse_qs(url.query)
        try:
            if path in ("/", "/index.html"):
                return self._static("index.html", head)
            if parts[0] == "static" and len(parts) == 2:
                return self._static(parts[1], head)
            if path == "/api/run":
                st.data.refresh()
                return self._json(st.run_info(), head)
            if path == "/api/data":
                st.data.refresh()
                return self._json(st.data.since(_int(q, "since", 0), _int(q, "tsince", 0)), head)
            if path == "/api/events":
                return self._events(_int(q, "since", 0), _int(q, "tsince", 0), head)
            if path == "/api/frame":
                return self._frame(q.get("topic", [""])[0], _int(q, "step", 0), head)
            if parts[0] == "mesh" and len(parts) == 2 and parts[1].isdigit():
                meshes = st.scene()["meshes"]
                i = int(parts[1])
                if i < len(meshes):
                    return self._file(meshes[i]["file"], head, cache=True)
                return self._error(HTTPStatus.NOT_FOUND, "no such mesh", head)
            if parts[0] == "run" and len(parts) >= 2:
                return self._run_file("/".join(parts[1:]), head)
        except (BrokenPipeError, ConnectionResetError):
            return
        return self._error(HTTPStatus.NOT_FOUND, "not found", head)

    def _static(self, name, head):
        p = self.state.static.get(name)
        if p is None:
            return self._error(HTTPStatus.NOT_FOUND, "not found", head)
        return self._file(p, head)

    def _run_file(self, rel: str, head):
        root = self.state.run_dir
        if posixpath.isabs(rel) or rel.startswith("~"):
            return self._error(HTTPStatus.FORBIDDEN, "forbidden path", head)
        try:
            target = (root / rel).resolve(strict=True)
        except (OSError, RuntimeError):
            return self._error(HTTPStatus.NOT_FOUND, "not found", head)
        if not target.is_relative_to(root) or not target.is_file():
            return self._error(HTTPStatus.FORBIDDEN, "outside the run directory", head)
        return self._file(target, head)

    def _frame(self, topic, step, head):
        try:
            got = self.state.data.frame(topic, step)
        except Exception:  # noqa: BLE001 - a part rewritten under us: the page asks again
            got = None
        if got is None:
            return self._error(HTTPStatus.NOT_FOUND, "no frame", head)
        s, arr = got
        self._send(HTTPStatus.OK, png_bytes(arr), "image/png", head, extra={"X-Frame-Step": str(s)}, cache=True)

    def _events(self, since: int, tsince: int, head):
        """Server-sent events: one ``data:`` line with everything new (the same JSON as
        /api/data?since=...) whenever the run directory gains steps or its status changes."""
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        if head:
            return
        data, st = self.state.data, self.state
        sent_version, last_beat = -1, time.monotonic()
        self.wfile.write(b"retry: 1000\n\n")
        self.wfile.flush()
        while not st.stopping.is_set():
            data.refresh()
            if data.version != sent_version:
                sent_version = data.version
                delta = data.since(since, tsince)
                msg = json.dumps(delta, separators=(",", ":"), allow_nan=False)
                self.wfile.write(b"data: " + msg.encode() + b"\n\n")
                self.wfile.flush()
                since, tsince = delta["next"]
                last_beat = time.monotonic()
            elif time.monotonic() - last_beat > 10:
                self.wfile.write(b": keep-alive\n\n")
                self.wfile.flush()
                last_beat = time.monotonic()
            st.stopping.wait(0.1 if data.running else 1.0)


def _int(q, key, default):
    try:
        return int(q.get(key, [default])[0])
    except (TypeError, ValueError):
        return default


class ViewServer:
    """A running view server (:func:`start_server`)."""

    def __init__(self, httpd: ThreadingHTTPServer, state: ViewState, thread: threading.Thread):
        self.httpd, self.state, self.thread = httpd, state, thread

    @property
    def port(self) -> int:
        return self.httpd.server_address[1]

    @property
    def url(self) -> str:
        host = self.httpd.server_address[0]
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    def stop(self):
        self.state.stopping.set()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


def make_server(run_dir, host: str = "127.0.0.1", port: int = 0, pending: bool = False):
    state = ViewState(run_dir, pending=pending)
    handler = type("BoundHandler", (Handler,), {"state": state})
    cls = ThreadingHTTPServer
    if ":" in host:
        import socket

        cls = type("V6Server", (ThreadingHTTPServer,), {"address_family": socket.AF_INET6})
    httpd = cls((host, port), handler)
    httpd.daemon_threads = True
    httpd.local_only = host in LOCAL_HOSTS
    return httpd, state


def start_server(run_dir, host: str = "127.0.0.1", port: int = 0, pending: bool = True) -> ViewServer:
    """Serves the view of ``run_dir`` from a background (daemon) thread and returns at
    once; ``.url`` is the page, ``.stop()`` ends it. With ``pending`` (the default, for
    ``caviar-core run --view``) the directory may not exist yet: the page waits for it."""
    httpd, state = make_server(run_dir, host, port, pending=pending)
    t = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.25}, name="caviar-view", daemon=True)
    t.start()
    return ViewServer(httpd, state, t)
