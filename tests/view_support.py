"""What the browser view's tests share: running the quickstart (and runs of small test
plugins) in a subprocess, the view's server on that run, and Debian's chromium driven by
playwright (software WebGL). Imported by tests/test_view.py and tests/test_view_serving.py."""

from __future__ import annotations

import http.client
import os
import pathlib
import subprocess
import sys
import textwrap

import pytest

from configs import episode, module

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


def live_config(steps: int, walkers: dict | None = None, link: dict | None = None) -> str:
    """A run of LIVE_PLUGINS (module view_live_plugins): the walkers and their link, ``steps``
    steps of 0.5 s, each module with its params where given."""
    return (episode(0.5, ["mobility", "communications"], steps=steps, seed=1)
            + module("walkers", "mobility", "view_live_plugins:Walkers", walkers)
            + module("link", "communications", "view_live_plugins:Link", link))


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
