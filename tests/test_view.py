"""`caviar-core view`: the page in a real browser (Debian's chromium driven by
playwright), live following, and image layers; the server's rules are in tests/test_view_serving.py.

Needs ``apt-get install chromium`` and ``pip install playwright`` (scripts/setup-view.sh);
the browser tests are skipped without them. ``CAVIAR_VIEW_DOCS=1`` also writes the
README's screenshot, docs/view-quickstart.png.
"""

from __future__ import annotations

import http.client
import io
import json
import os
import subprocess
import time
import urllib.parse

import polars as pl
import pytest

from caviar.view import RunData, start_server
from configs import episode, module
from view_support import (
    LIVE_PLUGINS,
    ROOT,
    assert_positions,
    live_config,
    open_page,
    request,
    run_caviar,
    run_with_plugins,
    view_state,
)

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




def test_live_run_newest_step_appears_within_2_s(browser, tmp_path):
    out = tmp_path / "live-run"
    proc = run_with_plugins(tmp_path, {"view_live_plugins": LIVE_PLUGINS},
                            live_config(30, link={"tx_position": [-154.0, 64.0, 120.0]}), out)
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
    cfg.write_text(episode(0.5, ["mobility"], steps=3, seed=1) + module(
        "layer", "mobility", "sample_plugins:ImageLayer", {"extent": LAYER_EXTENT, "z": LAYER_Z, "others": others}))
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
