"""`caviar-core view`: the page in a real browser (Debian's chromium driven by
playwright), live following, and the server's safety (read-only, no path escapes).

Needs ``apt-get install chromium`` and ``pip install playwright`` (scripts/setup-view.sh);
the browser tests are skipped without them. ``CAVIAR_VIEW_DOCS=1`` also writes the
README's screenshot, docs/view-quickstart.png.
"""

from __future__ import annotations

import http.client
import io
import json
import os
import pathlib
import shutil
import subprocess
import sys
import textwrap
import time
import urllib.parse

import polars as pl
import pytest

from caviar.view import RunData, start_server
from caviar.view.cli import main as view_main

ROOT = pathlib.Path(__file__).resolve().parent.parent
CHROMIUM = os.environ.get("CAVIAR_CHROMIUM", "/usr/bin/chromium")
# software WebGL (SwiftShader): headless machines have no GPU
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


def run_caviar(*args, env=None, **kw):
    return subprocess.Popen([sys.executable, "-m", "caviar.cli", *map(str, args)], env=env, **kw)


def run_with_plugins(tmp_path, plugins: dict[str, str], config: str, out):
    """`caviar-core run` of ``config`` (TOML, dedented) in ``tmp_path``, with the plugin
    modules ``plugins`` (name -> source) written there and importable; output piped."""
    for name, source in plugins.items():
        (tmp_path / f"{name}.py").write_text(source)
    cfg = tmp_path / "config.toml"
    cfg.write_text(textwrap.dedent(config))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    return run_caviar("run", cfg, "--out", out, "-q", env=env, cwd=tmp_path,
                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.fixture(scope="module")
def qs_run(tmp_path_factory):
    """The quickstart, recorded (1,525 steps, one UAV)."""
    out = tmp_path_factory.mktemp("view") / "qs"
    p = run_caviar("run", ROOT / "blueprints/quickstart/config.toml", "--out", out, "-q",
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log
    return out


@pytest.fixture(scope="module")
def positions(qs_run):
    m = pl.read_parquet(qs_run / "messages.parquet")
    m = m.filter(pl.col("topic") == "3D.mobility.positions")
    payloads = map(json.loads, m["text"].to_list())
    return {(s, d["UE_Id"]): d["position"] for s, d in zip(m["step"].to_list(), payloads, strict=True)}


@pytest.fixture(scope="module")
def server(qs_run):
    srv = start_server(qs_run, pending=False)
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    if not pathlib.Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} missing (apt-get install chromium)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def open_page(browser, url, requests=None):
    # bypass_csp: playwright evaluates its wait predicates as strings, which the page's CSP forbids
    page = browser.new_page(viewport={"width": 1400, "height": 820}, bypass_csp=True)
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    if requests is not None:
        page.on("request", lambda r: requests.append(r.url))
    page.goto(url)
    page.wait_for_function("window.caviarView && (caviarView.ready || caviarView.error)", timeout=20_000)
    assert page.evaluate("caviarView.error") is None
    return page, errors


def view_state(page):
    return page.evaluate("({step: caviarView.step, n: caviarView.entityCount, entities: caviarView.entities,"
                         " last: caviarView.lastStep, status: caviarView.status, following: caviarView.following,"
                         " beams: caviarView.beams, view: caviarView.viewPrimitives})")


def assert_positions(state, positions):
    assert state["entities"], state
    for ue, xyz in state["entities"].items():
        want = positions[(state["step"], ue)]
        assert xyz == pytest.approx([want["x"], want["y"], want["z"]], abs=2e-3), (ue, state["step"])


# ---------------------------------------------------------------------- the page


def test_page_draws_the_run_and_scrubbing_moves_the_entities(browser, server, positions, tmp_path):
    requests = []
    page, errors = open_page(browser, server.url, requests)
    page.wait_for_function("caviarView.meshesLoaded === caviarView.meshesTotal && caviarView.meshesTotal > 0",
                           timeout=20_000)
    s0 = view_state(page)
    assert s0["step"] == 0 and s0["last"] == 1524 and s0["status"] == "completed"
    assert s0["n"] == 1 == len({ue for (s, ue) in positions if s == 0})
    assert_positions(s0, positions)
    assert [b["ue"] for b in s0["beams"]] == ["uav1"]  # Tx -> served UE; LOS unknown without a link model
    assert s0["beams"][0]["los"] is None

    # scrub: click three-quarters along the timeline
    box = page.locator("#timeline").bounding_box()
    page.mouse.click(box["x"] + 0.75 * box["width"], box["y"] + box["height"] / 2)
    page.wait_for_function("caviarView.step > 0")
    s1 = view_state(page)
    assert 0.6 * 1524 < s1["step"] < 0.9 * 1524
    assert_positions(s1, positions)
    assert s1["entities"]["uav1"] != s0["entities"]["uav1"]
    page.keyboard.press("End")  # the slider has focus: the last step
    page.wait_for_function("caviarView.step === 1524")
    assert_positions(view_state(page), positions)

    # play at 50x for a moment: the step advances by itself
    page.locator("#timeline").press("Home")
    page.select_option("#speed", "50")
    page.click("#play")
    page.wait_for_function("caviarView.step > 100", timeout=10_000)
    page.click("#play")
    assert_positions(view_state(page), positions)

    page.mouse.click(box["x"] + 0.2 * box["width"], box["y"] + box["height"] / 2)
    page.wait_for_timeout(300)
    page.screenshot(path=tmp_path / "view-quickstart.png")
    if os.environ.get("CAVIAR_VIEW_DOCS"):
        page.screenshot(path=ROOT / "docs/view-quickstart.png")
    assert not errors
    origin = server.url.rstrip("/")
    assert all(u.startswith((origin + "/", "data:")) for u in requests), requests
    page.close()


# ---------------------------------------------------------------------- live runs

LIVE_PLUGINS = '''
import dataclasses
import math
import time

import numpy as np

import caviar


class Walkers(caviar.Plugin):
    """A UAV, a car and a pedestrian on circles, slowly (delay_s of wall time a step)."""

    @dataclasses.dataclass
    class Params:
        delay_s: float = 0.2

    def setup(self, ctx):
        self.ctx = ctx

    def step(self, t, inbox):
        time.sleep(self.ctx.params.delay_s)
        for i, (kind, r, z) in enumerate([("UAV", 80, 40), ("car", 120, 1), ("pedestrian", 60, 0)]):
            a = 0.2 * t + i
            position = {"x": -150 + r * math.cos(a), "y": 60 + r * math.sin(a), "z": z}
            yield "3D.mobility.positions", {"UE_type": kind, "UE_Id": f"{kind.lower()}{i}", "position": position}
        img = np.zeros((24, 32, 3), np.uint8)
        img[:, :, 0] = 8 * self.ctx.step
        yield "3D.camera.uav0", img  # a camera frame, as the camera plugin publishes it
        yield "view.walkers", {"points": [{"x": -150, "y": 60, "z": 0, "color": "#ff00ff", "label": "centre"}],
                               "lines": [{"points": [[-150, 60, 0], [-150, 60, 50]], "color": "#00ffff"}]}


class Link(caviar.Plugin):
    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params:
        tx_position: list = dataclasses.field(default_factory=lambda: [-154.0, 64.0, 120.0])

    def step(self, t, inbox):
        for m in inbox.on("3D.mobility.positions"):
            ue = m.data["UE_Id"]
            yield "communications.throughput", {"UE_type": m.data["UE_type"], "UE_Id": ue, "throughput": 100 + t}
            yield "communications.link", {"UE_Id": ue, "los": ue != "car1", "snr_db": 20 - t, "pair": 3}
'''


def test_live_run_newest_step_appears_within_2_s(browser, tmp_path):
    out = tmp_path / "live-run"
    proc = run_with_plugins(tmp_path, {"view_live_plugins": LIVE_PLUGINS}, """
        [episode]
        ts = 0.5
        steps = 30
        seed = 1
        stages = ["mobility", "communications"]
        [modules.walkers]
        stage = "mobility"
        plugin = "view_live_plugins:Walkers"
        [modules.link]
        stage = "communications"
        plugin = "view_live_plugins:Link"
        params = { tx_position = [-154.0, 64.0, 120.0] }
    """, out)
    srv = None
    try:
        deadline = time.monotonic() + 60
        while not (out / "messages").is_dir() or not list((out / "messages").glob("*.parquet")):
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, "the run wrote no part"
            time.sleep(0.05)
        srv = start_server(out, pending=False)
        page, errors = open_page(browser, srv.url)
        assert page.evaluate("caviarView.live") is True

        # watch parts land; the page must show each newest step within 2 s
        latencies, seen = [], {p.name for p in (out / "messages").glob("*.parquet")}
        while len(latencies) < 4 and proc.poll() is None:
            try:
                new = sorted({p.name for p in (out / "messages").glob("*.parquet")} - seen)
            except FileNotFoundError:
                break
            if not new:
                time.sleep(0.01)
                continue
            landed = time.monotonic()
            seen.update(new)
            step = int(pl.read_parquet(out / "messages" / new[-1], columns=["step"])["step"].max())
            page.wait_for_function(f"caviarView.step >= {step}", timeout=2_000)
            latencies.append(time.monotonic() - landed)
        assert len(latencies) == 4 and max(latencies) < 2.0, latencies
        st = view_state(page)
        assert st["following"] and st["n"] == 3
        assert {b["ue"]: b["los"] for b in st["beams"]} == {"uav0": True, "car1": False, "pedestrian2": True}
        assert st["view"] == 2  # view.walkers: a point (with its label) and a line
        page.wait_for_function("caviarView.frameTopic === '3D.camera.uav0' && caviarView.frameShown !== null"
                               " && document.getElementById('frame').complete")
        # The panel's image is the step it names (red = 8 × step), read in one go: a frame
        # loads off-screen and replaces the shown one only once decoded.
        for _ in range(5):
            frame, w, h, red, step = page.evaluate("""() => {
                const f = document.getElementById('frame'), c = document.createElement('canvas');
                c.width = f.naturalWidth; c.height = f.naturalHeight;
                const g = c.getContext('2d');
                g.drawImage(f, 0, 0);
                const red = c.width ? g.getImageData(0, 0, 1, 1).data[0] : null;
                return [caviarView.frameShown, f.naturalWidth, f.naturalHeight, red, caviarView.step];
            }""")
            assert frame <= step and [w, h] == [32, 24] and red == 8 * frame, (frame, w, h, red, step)
            time.sleep(0.1)

        assert proc.wait(timeout=60) == 0, proc.stdout.read()
        # the run finished: parts merged into messages.parquet; the page has every step
        page.wait_for_function("caviarView.status === 'completed' && caviarView.lastStep === 29", timeout=5_000)
        page.screenshot(path=tmp_path / "view-live.png")
        assert not errors
        page.close()
    finally:
        if proc.poll() is None:
            proc.kill()
        if srv:
            srv.stop()


def test_server_started_before_the_run_waits_for_it(tmp_path):
    srv = start_server(tmp_path / "not-yet")  # caviar-core run --view starts it before the first step
    try:
        c = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=5)
        c.request("GET", "/api/data")
        d = json.loads(c.getresponse().read())
        assert d["status"]["waiting"] and d["steps"] == []
    finally:
        srv.stop()


def test_run_with_view_serves_the_run_while_it_goes(tmp_path):
    """`caviar-core run CONFIG --view`: the URL comes before the first step, and the page's
    data follow the run (a slowed quickstart: 40 steps of at least 50 ms)."""
    out = tmp_path / "qs"
    p = run_caviar("run", ROOT / "blueprints/quickstart/config.toml", "--out", out, "-q", "--view",
                   "--set", "episode.steps=40", "--set", 'modules.slow.plugin="sample_plugins:Slow"',
                   "--set", 'modules.slow.stage="ai"', "--set", "modules.slow.params.seconds=0.05",
                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                   env={**os.environ, "PYTHONPATH": str(ROOT / "tests")})
    try:
        line = p.stderr.readline()
        while line.startswith("warning: "):  # the wiring warnings come first
            line = p.stderr.readline()
        assert line.startswith("view: http://127.0.0.1:"), line
        port = int(line.strip().rsplit(":", 1)[1].rstrip("/"))
        seen = []
        while p.poll() is None:
            try:
                c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                c.request("GET", "/api/data")
                seen.append(len(json.loads(c.getresponse().read())["steps"]))
                c.close()
            except OSError:  # the run ended, and its view with it
                assert p.poll() is not None or p.wait(timeout=5) is not None
            time.sleep(0.3)
        assert p.wait(timeout=60) == 0, p.stderr.read()
        assert any(0 < n < 40 for n in seen), seen  # followed the run while it went
    finally:
        p.kill()


# ---------------------------------------------------------------------- image layers

LAYER_EXTENT = [-300.0, 0.0, -50.0, 150.0]  # ImageLayer's: 3 rows of 200/3 m, 2 columns of 150 m
LAYER_Z = 200.0


@pytest.fixture(scope="module")
def layer_run(tmp_path_factory):
    """A run whose module writes PNGs into the run directory and draws one of them as a
    view.* image layer at step 0; at step 1 it names files the server must refuse."""
    base = tmp_path_factory.mktemp("layers")
    outside = base / "outside.png"
    outside.write_bytes(b"\x89PNG\r\n\x1a\n outside the run directory")
    out = base / "run"
    others = ["../outside.png", str(outside), "escape.png", "inside-link.png", "fake.png", "notes.txt",
              "./layer.png", "sub/../layer.png", "missing.png"]
    cfg = base / "layers.toml"
    cfg.write_text(textwrap.dedent(f"""
        [episode]
        ts = 0.5
        steps = 3
        seed = 1
        stages = ["mobility"]
        [modules.layer]
        stage = "mobility"
        plugin = "sample_plugins:ImageLayer"
        params = {{ extent = {LAYER_EXTENT}, z = {LAYER_Z}, others = {json.dumps(others)} }}
    """))
    p = run_caviar("run", cfg, "--out", out, "-q", stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                   env={**os.environ, "PYTHONPATH": str(ROOT / "tests")})
    log, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log
    (out / "escape.png").symlink_to(outside)  # named, but a link out of the run directory
    (out / "inside-link.png").symlink_to(out / "layer.png")  # named, a link that stays inside
    (out / "fake.png").write_text("not a PNG")
    (out / "notes.txt").write_text("text")
    return out


@pytest.fixture(scope="module")
def layer_server(layer_run):
    srv = start_server(layer_run, pending=False)
    yield srv
    srv.stop()


def layer_url(name):
    return "/api/layer?file=" + urllib.parse.quote(name, safe="")


def test_the_layer_route_serves_the_pngs_view_messages_name(layer_server, layer_run):
    for name in ("layer.png", "inside-link.png"):
        c = http.client.HTTPConnection("127.0.0.1", layer_server.port, timeout=5)
        c.request("GET", layer_url(name))
        r = c.getresponse()
        assert (r.status, r.getheader("Content-Type")) == (200, "image/png"), name
        assert r.read() == (layer_run / "layer.png").read_bytes()
        c.close()
    assert request(layer_server, "HEAD", layer_url("layer.png")) == (200, b"")


@pytest.mark.parametrize("name", [
    "unnamed.png",  # a PNG in the run directory that no view.* message names
    "../outside.png", "escape.png",  # named: out of the run directory, by name and by link
    "fake.png", "notes.txt",  # named: not a PNG
    "./layer.png", "sub/../layer.png",  # named, but not as a plain relative path
    "missing.png", "config.toml", "run.json", "", "layer.PNG", "/layer.png", "layer.png\x00",
    "messages.parquet", "%2e%2e/outside.png",
])
def test_the_layer_route_refuses_everything_else(layer_server, layer_run, name):
    status, body = request(layer_server, "GET", layer_url(name))
    assert status == 404 and not body.startswith(b"\x89PNG"), (name, status)


def test_the_layer_route_refuses_absolute_paths_even_when_named(layer_server, layer_run):
    outside = layer_run.parent / "outside.png"
    assert str(outside) in RunData(layer_run).view_images  # the module named it
    for name in (str(outside), "/etc/passwd", str(layer_run / "layer.png")):
        assert request(layer_server, "GET", layer_url(name))[0] == 404, name
    assert request(layer_server, "GET", "/api/layer?file=../outside.png")[0] == 404
    assert request(layer_server, "GET", "/api/layer")[0] == 404


def test_the_page_draws_image_layers_and_the_box_hides_them(browser, layer_server):
    """The layer is a plane at its height over its extent, its first row north, its
    transparent pixels see-through; unchecking "layers" hides it."""
    image = pytest.importorskip("PIL.Image", reason="pillow (matplotlib's) reads the screenshots")
    page, errors = open_page(browser, layer_server.url)
    page.wait_for_function("caviarView.imageLayersLoaded === 1 && caviarView.meshesLoaded === caviarView.meshesTotal",
                           timeout=20_000)
    assert page.evaluate("[caviarView.step, caviarView.imageLayers, caviarView.imageLayersShown]") == [0, 1, 1]
    x0, x1, y0, y1 = LAYER_EXTENT
    row = (y1 - y0) / 3
    spots = {name: page.evaluate(f"caviarView.project({(x0 + x1) / 2}, {y1 - (i + 0.5) * row}, {LAYER_Z})")
             for i, name in enumerate(["red", "blue", "clear"])}

    def pixels():
        img = image.open(io.BytesIO(page.screenshot())).convert("RGB")
        return {k: img.getpixel((round(x), round(y))) for k, (x, y) in spots.items()}

    def toggle():
        r = page.evaluate("caviarView.renders")
        page.click("#layers")
        page.wait_for_function(f"caviarView.renders > {r}")  # drawn since

    page.wait_for_timeout(300)  # the frame after the texture came
    shown = pixels()
    r, g, b = shown["red"]
    assert r > 200 and g < 60 and b < 60, shown
    r, g, b = shown["blue"]
    assert b > 200 and r < 60 and g < 60, shown
    toggle()
    assert page.evaluate("caviarView.imageLayersShown") == 0
    assert page.evaluate("caviarView.imageLayers") == 1
    hidden = pixels()
    assert hidden["red"] != shown["red"] and hidden["blue"] != shown["blue"]
    assert hidden["clear"] == pytest.approx(shown["clear"], abs=8)  # alpha 0: what is under it shows
    toggle()
    assert page.evaluate("caviarView.imageLayersShown") == 1
    assert pixels()["red"] == shown["red"]
    assert not errors
    page.close()


# ---------------------------------------------------------------------- safety


def request(server, method, path, host=None):
    c = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    c.putrequest(method, path, skip_host=host is not None, skip_accept_encoding=True)
    if host is not None:
        c.putheader("Host", host)
    c.endheaders()
    r = c.getresponse()
    body = r.read()
    c.close()
    return r.status, body


@pytest.mark.parametrize("path", [
    "/../../../../etc/passwd", "/static/../server.py", "/static/..%2fserver.py", "/static/%2e%2e/server.py",
    "/run/../../../../etc/passwd", "/run/%2e%2e/%2e%2e/%2e%2e/etc/passwd", "/run/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd",
    "/run//etc/passwd", "/run/%2Fetc%2Fpasswd", "/run/~/.bashrc", "/run/outside-link", "/run/artifacts/../../x",
    "/mesh/../../etc/passwd", "/mesh/99", "/mesh/-1", "/etc/passwd", "/static/view.js%00.html", "/run/config.toml%00",
])
def test_paths_outside_what_the_view_serves_are_refused(server, qs_run, path):
    link = qs_run / "outside-link"
    if not link.is_symlink():
        link.symlink_to("/etc/passwd")
    status, body = request(server, "GET", path)
    assert status in (400, 403, 404), (path, status)
    assert b"root:" not in body


def test_what_the_view_serves(server, qs_run):
    (qs_run / "inside-link").unlink(missing_ok=True)
    (qs_run / "inside-link").symlink_to(qs_run / "config.toml")
    assert request(server, "GET", "/run/config.toml") == (200, (qs_run / "config.toml").read_bytes())
    assert request(server, "GET", "/run/inside-link")[0] == 200  # a link that stays inside
    assert request(server, "GET", "/mesh/0")[1].startswith(b"ply")
    assert request(server, "GET", "/static/view.js")[0] == 200
    assert request(server, "HEAD", "/") == (200, b"")


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH", "OPTIONS", "PROPFIND"])
def test_only_get_and_head(server, method):
    status, _ = request(server, method, "/")
    assert status in (405, 501)


def test_other_hosts_are_refused_on_localhost(server):  # DNS rebinding
    assert request(server, "GET", "/api/run", host="evil.example:80")[0] == 403
    assert request(server, "GET", "/api/run", host=f"localhost:{server.port}")[0] == 200


# ---------------------------------------------------------------------- errors


def test_bad_run_directories_are_clear_errors(tmp_path, qs_run, capsys):
    bad = {"missing": tmp_path / "nope", "file": tmp_path / "a-file", "empty": tmp_path / "empty",
           "corrupt-status": tmp_path / "cs", "corrupt-parquet": tmp_path / "cp"}
    bad["file"].write_text("x")
    bad["empty"].mkdir()
    for k in ("corrupt-status", "corrupt-parquet"):
        shutil.copytree(qs_run, bad[k], symlinks=True)
    (bad["corrupt-status"] / "run.json").write_text("{not json")
    (bad["corrupt-parquet"] / "messages.parquet").write_bytes(b"PAR1 garbage")
    for name, path in bad.items():
        assert view_main([str(path), "--port", "0"]) == 2, name
        err = capsys.readouterr().err
        assert str(path) in err and "Traceback" not in err, (name, err)
    # and as a command, without a traceback
    p = subprocess.run([sys.executable, "-m", "caviar.view", str(bad["missing"])], capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 2 and str(bad["missing"]) in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_run_data_reads_what_was_recorded(qs_run, positions):
    d = RunData(qs_run)
    assert len(d.step_time) == 1525
    assert len(d.entities["uav1"]["p"]) == len(positions)
    assert d.since(1500)["steps"][0] == [1500, pytest.approx(150.0)]


# Replaces the parts of a live run by the compacted table, and back, for DURATION s:
# what the recorder does once at the end of a run (and, for chunks, every 256 parts),
# over and over, each state held HOLD s (a recorder changes its files at most once a step).
# At every moment one complete copy of the messages is on disk.
TOGGLER = r'''
import os, pathlib, shutil, sys, time
run, duration, hold = pathlib.Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[4])
parts = {p.name: p.read_bytes() for p in sorted((run / "messages").glob("part-*.parquet"))}
compacted = pathlib.Path(sys.argv[3]).read_bytes()
print("ready", flush=True)
end, n = time.monotonic() + duration, 0
while time.monotonic() < end:
    (run / "messages.tmp").write_bytes(compacted)
    os.replace(run / "messages.tmp", run / "messages.parquet")  # the compacted table lands,
    shutil.rmtree(run / "messages")                              # then the parts go
    time.sleep(hold)
    new = run / "messages.new"
    new.mkdir()
    for name, b in parts.items():
        (new / name).write_bytes(b)
    os.replace(new, run / "messages")                             # the parts come back,
    (run / "messages.parquet").unlink()                           # then the table goes
    time.sleep(hold)
    n += 1
print(n, flush=True)
'''


def test_a_frame_is_served_while_its_part_is_merged_away(tmp_path, monkeypatch):
    """The live view's camera frame is read from the part that held it when indexed; the
    recorder may merge that part away between the listing and the read. The frame must
    still come back (from the merged file), never a 404 that the page shows as a broken
    image (the flaky live-view test of 2026-11-26)."""
    import caviar

    (tmp_path / "view_live_plugins.py").write_text(LIVE_PLUGINS)
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = tmp_path / "live.toml"
    cfg.write_text(textwrap.dedent("""
        [episode]
        ts = 0.5
        steps = 10
        seed = 1
        stages = ["mobility", "communications"]
        [modules.walkers]
        stage = "mobility"
        plugin = "view_live_plugins:Walkers"
        params = { delay_s = 0.0 }
        [modules.link]
        stage = "communications"
        plugin = "view_live_plugins:Link"
    """))
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "recording") as sim:
        for _ in range(4):
            sim.step()
        run = tmp_path / "run"  # the run as it was after 4 steps: parts, no compacted table
        shutil.copytree(tmp_path / "recording", run)
    assert not (run / "messages.parquet").exists()
    data = RunData(run)
    assert sorted(data.frames["3D.camera.uav0"]) == [0, 1, 2, 3]
    assert all(f.parent == run / "messages" for f in data.frames["3D.camera.uav0"].values())
    pl.concat([pl.read_parquet(p) for p in sorted((run / "messages").glob("part-*.parquet"))]).write_parquet(
        tmp_path / "compacted.parquet")
    toggler = subprocess.Popen([sys.executable, "-c", TOGGLER, str(run), "2.0", str(tmp_path / "compacted.parquet"),
                                "0.005"],
                               stdout=subprocess.PIPE, text=True)
    try:
        assert toggler.stdout.readline().strip() == "ready"
        got = []
        while toggler.poll() is None:
            step = len(got) % 4
            f = data.frame("3D.camera.uav0", step)
            got.append(None if f is None else (f[0], int(f[1][0, 0, 0]), f[1].shape))
            assert got[-1] == (step, 8 * step, (24, 32, 3)), (len(got), got[-1])
        cycles = int(toggler.stdout.read().strip())
    finally:
        toggler.kill()
        toggler.wait()
    assert toggler.returncode == 0 and cycles > 50 and len(got) > 50, (toggler.returncode, cycles, len(got))


BAD_FRAME_PLUGINS = '''
import numpy as np

import caviar


class Camera(caviar.Plugin):
    """A 32×24 frame a step, red = 8 × step; step 3's has two channels, which no PNG holds."""

    def step(self, t, inbox):
        img = np.zeros((24, 32, 2 if self.ctx.step == 3 else 3), np.uint8)
        img[:, :, 0] = 8 * self.ctx.step
        yield "3D.camera.uav0", img

    def setup(self, ctx):
        self.ctx = ctx
'''


def test_a_frame_the_server_cannot_give_leaves_the_last_one_dimmed_and_said(browser, tmp_path):
    out = tmp_path / "run"
    p = run_with_plugins(tmp_path, {"bad_frame_plugins": BAD_FRAME_PLUGINS}, """
        [episode]
        ts = 0.5
        steps = 6
        seed = 1
        stages = ["camera"]
        [modules.camera]
        stage = "camera"
        plugin = "bad_frame_plugins:Camera"
    """, out)
    assert p.wait(timeout=60) == 0, p.stdout.read()
    srv = start_server(out, pending=False)
    try:
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
        conn.request("GET", "/api/frame?topic=3D.camera.uav0&step=3")
        assert conn.getresponse().status == 404  # two channels: no frame to give
        page, errors = open_page(browser, srv.url)
        shown = """() => {
            const f = document.getElementById('frame'), c = document.createElement('canvas');
            c.width = f.naturalWidth; c.height = f.naturalHeight;
            const g = c.getContext('2d');
            g.drawImage(f, 0, 0);
            return {step: caviarView.step, frame: caviarView.frameShown, size: [f.naturalWidth, f.naturalHeight],
                    red: c.width ? g.getImageData(0, 0, 1, 1).data[0] : null, stale: f.classList.contains('stale'),
                    note: document.getElementById('framenote').textContent};
        }"""

        def go(step):
            page.evaluate(f"(() => {{ const t = document.getElementById('timeline'); t.value = {step};"
                          " t.dispatchEvent(new Event('input')); })()")

        def wait(condition):
            try:
                page.wait_for_function(condition, timeout=10_000)
            except Exception:  # noqa: BLE001 - say what the page shows
                topic = page.evaluate("caviarView.frameTopic")
                raise AssertionError(f"{condition}: {page.evaluate(shown)}, topic {topic}") from None

        # a finished run opens at its first step, and shows its frame without being touched
        wait("caviarView.frameShown === 0")
        assert page.evaluate(shown) == {"step": 0, "frame": 0, "size": [32, 24], "red": 0, "stale": False,
                                        "note": "3D.camera.uav0 · step 0"}
        go(4)
        wait("caviarView.frameShown === 4")
        assert page.evaluate(shown) == {"step": 4, "frame": 4, "size": [32, 24], "red": 32, "stale": False,
                                        "note": "3D.camera.uav0 · step 4"}
        go(3)
        wait("document.getElementById('framenote').textContent.includes('unavailable')")
        time.sleep(1.2)  # its retries (3, 0.3 s apart) fail too
        assert page.evaluate(shown) == {"step": 3, "frame": 4, "size": [32, 24], "red": 32, "stale": True,
                                        "note": "3D.camera.uav0: frame of step 3 unavailable"}
        go(2)
        wait("caviarView.frameShown === 2")
        assert page.evaluate(shown) == {"step": 2, "frame": 2, "size": [32, 24], "red": 16, "stale": False,
                                        "note": "3D.camera.uav0 · step 2"}
        assert not errors
    finally:
        srv.stop()
