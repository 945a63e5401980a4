"""The view's HTTP server: read-only (GET and HEAD), standard library only.

It serves its own static files (by exact name), the run's data as JSON, live updates
as server-sent events, camera frames as PNG, files under the run directory (resolved,
symbolic links included, and refused if they land outside it), the scene meshes
the run's scene XML references (by index into that allow-list, never by path), and the
PNG image layers that ``view.*`` messages name (``/api/layer?file=NAME``: only a name an
``images`` entry of a recorded message gives, a relative path ending in ``.png`` that
resolves, links included, to a PNG file inside the run directory; anything else is 404).
"""

from __future__ import annotations

import json
import os
import pathlib
import posixpath
import socket
import sys
import threading
import time
import urllib.parse
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from caviar.view.data import RunData, png_bytes
from caviar.view.scene import find_scene, scene_meshes, transmitter

STATIC = pathlib.Path(__file__).parent / "static"
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
         ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8", ".json": "application/json",
         ".png": "image/png", ".jpg": "image/jpeg", ".csv": "text/csv; charset=utf-8",
         ".ply": "application/octet-stream", ".toml": "text/plain; charset=utf-8", ".svg": "image/svg+xml"}
CSP = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
       "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1", "[::1]"}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ViewState:
    """What the handlers share: the run's data, its scene and the allow-lists."""

    def __init__(self, run_dir: str | os.PathLike[str], pending: bool = False):
        self.data = RunData(run_dir, pending=pending)
        self.static: dict[str, pathlib.Path] = (
            {p.name: p for p in STATIC.iterdir() if p.is_file() and not p.is_symlink()} if STATIC.is_dir() else {})
        self.stopping = threading.Event()
        self._scene: dict[str, Any] | None = None
        self._scene_lock = threading.Lock()

    @property
    def run_dir(self) -> pathlib.Path:
        return self.data.path.resolve()

    def scene(self) -> dict[str, Any]:
        with self._scene_lock:
            sc = self._scene
            if sc is None or (not sc["had_config"] and self.data.config):
                cfg = self.data.config
                cf = self.data.status.get("config_file")
                config_dir = pathlib.Path(cf).parent if isinstance(cf, str) and cf else None
                name, xml, origin = find_scene(cfg, config_dir, self.data.path, self.data.contract)
                meshes: list[dict[str, Any]] = []
                if xml is not None:
                    try:
                        meshes = scene_meshes(xml)
                    except Exception as e:  # noqa: BLE001 - a bad scene must not stop the view
                        origin += f"; unreadable scene XML: {e}"
                sc = self._scene = {"name": name, "xml": str(xml) if xml else None, "origin": origin,
                                    "meshes": meshes, "tx": transmitter(cfg, self.data.contract),
                                    "had_config": bool(cfg)}
            return sc

    def run_info(self) -> dict[str, Any]:
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
            "contract": self.data.contract.for_page(),
        }


class ViewHTTPServer(ThreadingHTTPServer):
    """The view's server: a thread per request; ``local_only`` (bound to a local
    address) refuses requests whose Host is not a local name (DNS rebinding)."""

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler], local_only: bool):
        super().__init__(address, handler)
        self.local_only = local_only

    @property
    def host(self) -> str:
        """The address it listens on, bracketed if IPv6."""
        host = self.server_address[0]
        host = host.decode() if isinstance(host, (bytes, bytearray)) else host
        return f"[{host}]" if ":" in host else host

    @property
    def port(self) -> int:
        return self.server_address[1]

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"


class ViewHTTPServer6(ViewHTTPServer):
    address_family = socket.AF_INET6


class Handler(BaseHTTPRequestHandler):
    server_version = "caviar-view"
    sys_version = ""
    protocol_version = "HTTP/1.1"
    state: ViewState  # set on the subclass made per server
    server: ViewHTTPServer

    def log_message(self, fmt: str, *args: Any) -> None:  # quiet: the page polls nothing but SSE keeps it busy
        if os.environ.get("CAVIAR_VIEW_LOG"):
            sys.stderr.write("view: " + fmt % args + "\n")

    # ---- methods -----------------------------------------------------------------------

    def _refuse_method(self) -> None:
        self._send(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only: GET and HEAD only\n", "text/plain; charset=utf-8",
                   extra={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_CONNECT = do_TRACE = _refuse_method

    def do_HEAD(self) -> None:
        self._get(head=True)

    def do_GET(self) -> None:
        self._get(head=False)

    # ---- responses ----------------------------------------------------------------------

    def _send(self, code: int, body: bytes, ctype: str, head: bool = False, extra: dict[str, str] | None = None,
              cache: bool = False) -> None:
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

    def _error(self, code: int, msg: str, head: bool) -> None:
        self._send(code, (msg + "\n").encode(), "text/plain; charset=utf-8", head)

    def _json(self, obj: Any, head: bool) -> None:
        self._send(HTTPStatus.OK, json.dumps(obj, separators=(",", ":"), allow_nan=False).encode(),
                   "application/json", head)

    def _file(self, path: pathlib.Path, head: bool, cache: bool = False) -> None:
        try:
            body = path.read_bytes()
        except OSError:
            self._error(HTTPStatus.NOT_FOUND, "not found", head)
            return
        self._send(HTTPStatus.OK, body, TYPES.get(path.suffix.lower(), "application/octet-stream"), head, cache=cache)

    # ---- routing ------------------------------------------------------------------------

    def _host(self) -> str:
        """The host name of the request's Host header ("" if none or malformed)."""
        try:
            return urllib.parse.urlsplit("//" + (self.headers.get("Host") or "")).hostname or ""
        except ValueError:
            return ""

    def _get(self, head: bool) -> None:
        if self.server.local_only and self._host() not in LOCAL_HOSTS:  # DNS rebinding
            self._error(HTTPStatus.FORBIDDEN, "forbidden host", head)
            return
        url = urllib.parse.urlsplit(self.path)
        path = urllib.parse.unquote(url.path)
        if "\x00" in path or "\\" in path or not path.startswith("/"):
            self._error(HTTPStatus.BAD_REQUEST, "bad path", head)
            return
        parts = path.split("/")[1:]
        if any(p in ("..", ".") for p in parts) or "//" in path:
            self._error(HTTPStatus.FORBIDDEN, "forbidden path", head)
            return
        try:
            if self._route(path, parts, urllib.parse.parse_qs(url.query), head):
                return
        except (BrokenPipeError, ConnectionResetError):
            return
        self._error(HTTPStatus.NOT_FOUND, "not found", head)

    def _route(self, path: str, parts: list[str], q: dict[str, list[str]], head: bool) -> bool:
        """Answers a checked path; False if nothing is there."""
        if path in ("/", "/index.html"):
            self._static("index.html", head)
        elif parts[0] == "static" and len(parts) == 2:
            self._static(parts[1], head)
        elif parts[0] == "api":
            return self._api(path, q, head)
        elif parts[0] == "mesh" and len(parts) == 2 and parts[1].isdigit():
            self._mesh(int(parts[1]), head)
        elif parts[0] == "run" and len(parts) >= 2:
            self._run_file("/".join(parts[1:]), head)
        else:
            return False
        return True

    def _api(self, path: str, q: dict[str, list[str]], head: bool) -> bool:
        st = self.state
        if path == "/api/run":
            st.data.refresh()
            self._json(st.run_info(), head)
        elif path == "/api/data":
            st.data.refresh()
            self._json(st.data.since(_int(q, "since", 0), _int(q, "tsince", 0)), head)
        elif path == "/api/events":
            self._events(_int(q, "since", 0), _int(q, "tsince", 0), head)
        elif path == "/api/frame":
            self._frame(q.get("topic", [""])[0], _int(q, "step", 0), head)
        elif path == "/api/layer":
            self._layer(q.get("file", [""])[0], head)
        else:
            return False
        return True

    def _mesh(self, i: int, head: bool) -> None:
        meshes = self.state.scene()["meshes"]
        if i < len(meshes):
            self._file(meshes[i]["file"], head, cache=True)
        else:
            self._error(HTTPStatus.NOT_FOUND, "no such mesh", head)

    def _static(self, name: str, head: bool) -> None:
        p = self.state.static.get(name)
        if p is None:
            self._error(HTTPStatus.NOT_FOUND, "not found", head)
        else:
            self._file(p, head)

    def _run_file(self, rel: str, head: bool) -> None:
        root = self.state.run_dir
        if posixpath.isabs(rel) or rel.startswith("~"):
            self._error(HTTPStatus.FORBIDDEN, "forbidden path", head)
            return
        try:
            target = (root / rel).resolve(strict=True)
        except (OSError, RuntimeError):
            self._error(HTTPStatus.NOT_FOUND, "not found", head)
            return
        if not target.is_relative_to(root) or not target.is_file():
            self._error(HTTPStatus.FORBIDDEN, "outside the run directory", head)
            return
        self._file(target, head)

    def _layer(self, name: str, head: bool) -> None:
        """An image layer of a ``view.*`` message: the PNG ``name`` in the run directory, if
        a recorded message names it; 404 for anything else (which says nothing of what exists)."""
        target = self._layer_file(name)
        if target is None:
            self._error(HTTPStatus.NOT_FOUND, "no such layer", head)
            return
        try:
            body = target.read_bytes()
        except OSError:
            body = b""
        if not body.startswith(PNG_SIGNATURE):
            self._error(HTTPStatus.NOT_FOUND, "no such layer", head)
            return
        self._send(HTTPStatus.OK, body, "image/png", head)

    def _layer_file(self, name: str) -> pathlib.Path | None:
        parts = name.split("/")
        if (not name or "\x00" in name or "\\" in name or name.startswith("~") or posixpath.isabs(name)
                or any(p in ("", ".", "..") for p in parts) or not name.lower().endswith(".png")):
            return None
        st = self.state
        st.data.refresh()
        if not st.data.names_image(name):
            return None
        root = st.run_dir
        try:
            target = (root / name).resolve(strict=True)
        except (OSError, RuntimeError):
            return None
        if not target.is_relative_to(root) or not target.is_file() or target.suffix.lower() != ".png":
            return None
        return target

    def _frame(self, topic: str, step: int, head: bool) -> None:
        try:
            got = self.state.data.frame(topic, step)
        except Exception:  # noqa: BLE001 - a part rewritten under us: the page asks again
            got = None
        if got is None:
            self._error(HTTPStatus.NOT_FOUND, "no frame", head)
            return
        s, arr = got
        self._send(HTTPStatus.OK, png_bytes(arr), "image/png", head, extra={"X-Frame-Step": str(s)}, cache=True)

    def _events(self, since: int, tsince: int, head: bool) -> None:
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


def _int(q: dict[str, list[str]], key: str, default: int) -> int:
    try:
        return int(q.get(key, [default])[0])
    except (TypeError, ValueError):
        return default


class ViewServer:
    """A running view server (:func:`start_server`)."""

    def __init__(self, httpd: ViewHTTPServer, state: ViewState, thread: threading.Thread):
        self.httpd, self.state, self.thread = httpd, state, thread

    @property
    def port(self) -> int:
        return self.httpd.port

    @property
    def url(self) -> str:
        return self.httpd.url

    def stop(self) -> None:
        self.state.stopping.set()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


def make_server(run_dir: str | os.PathLike[str], host: str = "127.0.0.1", port: int = 0,
                pending: bool = False) -> tuple[ViewHTTPServer, ViewState]:
    state = ViewState(run_dir, pending=pending)
    handler = type("BoundHandler", (Handler,), {"state": state})
    cls = ViewHTTPServer6 if ":" in host else ViewHTTPServer
    httpd = cls((host, port), handler, local_only=host in LOCAL_HOSTS)
    httpd.daemon_threads = True
    return httpd, state


def start_server(run_dir: str | os.PathLike[str], host: str = "127.0.0.1", port: int = 0,
                 pending: bool = True) -> ViewServer:
    """Serves the view of ``run_dir`` from a background (daemon) thread and returns at
    once; ``.url`` is the page, ``.stop()`` ends it. With ``pending`` (the default, for
    ``caviar-core run --view``) the directory may not exist yet: the page waits for it."""
    httpd, state = make_server(run_dir, host, port, pending=pending)
    t = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.25}, name="caviar-view",
                         daemon=True)
    t.start()
    return ViewServer(httpd, state, t)
