"""`caviar-core view`: the server's safety (read-only, GET and HEAD only, localhost, no path
escapes), what it serves of a recorded run, and camera frames served while the recorder
merges their parts (a real browser for the frame panel). Shared parts: tests/view_support.py."""

from __future__ import annotations

import http.client
import shutil
import subprocess
import sys
import time

import polars as pl
import pytest

from caviar.view import RunData, start_server
from caviar.view.cli import main as view_main
from configs import episode, module
from view_support import (
    LIVE_PLUGINS,
    live_config,
    open_page,
    request,
    run_with_plugins,
)

# ---------------------------------------------------------------------- safety


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
    cfg.write_text(live_config(10, walkers={"delay_s": 0.0}))
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
    p = run_with_plugins(tmp_path, {"bad_frame_plugins": BAD_FRAME_PLUGINS}, episode(0.5, ["camera"], steps=6, seed=1)
                         + module("camera", "camera", "bad_frame_plugins:Camera"), out)
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

        def shows(step, frame, red, note, stale=False):  # what the frame panel shows (32 x 24, red = 8 x step)
            assert page.evaluate(shown) == {"step": step, "frame": frame, "size": [32, 24], "red": red,
                                            "stale": stale, "note": note}

        # a finished run opens at its first step, and shows its frame without being touched
        wait("caviarView.frameShown === 0")
        shows(0, 0, 0, "3D.camera.uav0 · step 0")
        go(4)
        wait("caviarView.frameShown === 4")
        shows(4, 4, 32, "3D.camera.uav0 · step 4")
        go(3)
        wait("document.getElementById('framenote').textContent.includes('unavailable')")
        time.sleep(1.2)  # its retries (3, 0.3 s apart) fail too
        shows(3, 4, 32, "3D.camera.uav0: frame of step 3 unavailable", stale=True)
        go(2)
        wait("caviarView.frameShown === 2")
        shows(2, 2, 16, "3D.camera.uav0 · step 2")
        assert not errors
    finally:
        srv.stop()
