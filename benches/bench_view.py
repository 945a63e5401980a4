"""Benchmark of `caviar-core view` (not a test): page load time of a 2,000-step run with
50 entities, and the frame rate while it plays, measured in the browser
(requestAnimationFrame callbacks and renders over a few seconds) in headless Debian
chromium with software WebGL (SwiftShader). Writes docs/results/view/bench.json.

    python benches/bench_view.py [--steps 2000] [--entities 50] [--seconds 5] [--reps 3]

Needs what tests/test_view.py needs (chromium, playwright; scripts/setup-view.sh).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUT = ROOT / "docs/results/view/bench.json"
CHROMIUM = os.environ.get("CAVIAR_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]

CROWD = '''
import dataclasses
import math

import caviar

KINDS = ["UAV", "car", "pedestrian"]


class Crowd(caviar.Plugin):
    """n entities on circles around the Central Park scene's centre, one message each a step."""

    @dataclasses.dataclass
    class Params:
        n: int = 50

    def step(self, t, inbox):
        for i in range(self.ctx.params.n):
            kind = KINDS[i % 3]
            r, z = 40 + 5 * i, {"UAV": 40.0, "car": 1.0, "pedestrian": 0.0}[kind]
            a = 0.05 * t * (1 + i % 7) + i
            yield "3D.mobility.positions", {"UE_type": kind, "UE_Id": f"{kind.lower()}{i}",
                                             "position": {"x": -150 + r * math.cos(a), "y": 60 + r * math.sin(a),
                                                          "z": z}}


class Link(caviar.Plugin):
    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params:
        tx_position: list = dataclasses.field(default_factory=lambda: [-154.0, 64.0, 120.0])

    def step(self, t, inbox):
        for m in inbox.on("3D.mobility.positions"):
            p = m.data["position"]
            d = math.dist((p["x"], p["y"], p["z"]), self.ctx.params.tx_position)
            yield "communications.throughput", {"UE_type": m.data["UE_type"], "UE_Id": m.data["UE_Id"],
                                                "throughput": 2000.0 / (1 + d / 50)}
            yield "communications.link", {"UE_Id": m.data["UE_Id"], "los": d < 200, "snr_db": 40 - 20 * math.log10(d)}
'''


def make_run(tmp: pathlib.Path, steps: int, n: int) -> tuple[pathlib.Path, float]:
    (tmp / "bench_view_plugins.py").write_text(CROWD)
    cfg = tmp / "crowd.toml"
    cfg.write_text(textwrap.dedent(f"""
        [episode]
        ts = 0.1
        steps = {steps}
        seed = 1
        stages = ["mobility", "communications"]
        [modules.crowd]
        stage = "mobility"
        plugin = "bench_view_plugins:Crowd"
        params = {{ n = {n} }}
        [modules.link]
        stage = "communications"
        plugin = "bench_view_plugins:Link"
    """))
    out = tmp / "crowd-run"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp), os.environ.get("PYTHONPATH", "")]))
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "caviar.cli", "run", str(cfg), "--out", str(out), "-q"], env=env, check=True)
    return out, time.perf_counter() - t


def cpu_model() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"


FPS_JS = """async (seconds) => {
  const r0 = caviarView.renders;
  let frames = 0;
  const t0 = performance.now();
  await new Promise((done) => {
    const tick = (now) => { frames++; if (now - t0 < seconds * 1000) requestAnimationFrame(tick); else done(); };
    requestAnimationFrame(tick);
  });
  const dt = (performance.now() - t0) / 1000;
  return {seconds: dt, raf_per_s: frames / dt, renders_per_s: (caviarView.renders - r0) / dt};
}"""

GL_JS = """() => {
  const canvas = document.createElement('canvas');
  const gl = canvas.getContext('webgl2') || canvas.getContext('webgl');
  if (!gl) return null;
  const ext = gl.getExtension('WEBGL_debug_renderer_info');
  return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--entities", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    args = ap.parse_args(argv)

    from playwright.sync_api import sync_playwright

    from caviar.view import RunData, start_server

    with tempfile.TemporaryDirectory(prefix="bench-view-") as d:
        run, run_s = make_run(pathlib.Path(d), args.steps, args.entities)
        print(f"recorded {args.steps} steps x {args.entities} entities in {run_s:.1f} s", flush=True)
        t = time.perf_counter()
        RunData(run)
        read_s = time.perf_counter() - t
        srv = start_server(run, pending=False)
        try:
            import urllib.request

            t = time.perf_counter()
            payload = len(urllib.request.urlopen(srv.url + "api/data?since=0").read())
            data_s = time.perf_counter() - t
            loads, fps = [], None
            with sync_playwright() as p:
                b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                for _ in range(args.reps):
                    page = b.new_page(viewport={"width": 1400, "height": 820}, bypass_csp=True)
                    t = time.perf_counter()
                    page.goto(srv.url)
                    page.wait_for_function("window.caviarView && caviarView.ready && caviarView.renders > 0"
                                           " && caviarView.meshesLoaded === caviarView.meshesTotal", timeout=60_000,
                                           polling=20)
                    loads.append(time.perf_counter() - t)
                    n = page.evaluate("caviarView.entityCount")
                    page.close()
                page = b.new_page(viewport={"width": 1400, "height": 820}, bypass_csp=True)
                page.goto(srv.url)
                page.wait_for_function("caviarView.ready && caviarView.meshesLoaded === caviarView.meshesTotal")
                gl = page.evaluate(GL_JS)
                idle = page.evaluate(FPS_JS, args.seconds)  # nothing changes: the page renders nothing
                page.select_option("#speed", "10")
                page.click("#play")
                s0 = page.evaluate("caviarView.step")
                fps = page.evaluate(FPS_JS, args.seconds)
                s1 = page.evaluate("caviarView.step")
                parts = page.evaluate("caviarView.frameMs")
                page.screenshot(path=str(pathlib.Path(d) / "bench.png"))
                version = b.version
                b.close()
        finally:
            srv.stop()

    result = {
        "what": "caviar-core view: page load and frame rate, headless chromium with software WebGL",
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "os": platform.platform(),
                    "browser": f"Debian chromium {version} (headless, playwright)", "webgl": gl,
                    "viewport": "1400x820", "note": "2 cores shared with other work; no GPU"},
        "run": {"steps": args.steps, "entities": args.entities, "messages_per_step": 3 * args.entities,
                "record_s": round(run_s, 2)},
        "server": {"read_run_s": round(read_s, 3), "api_data_bytes": payload, "api_data_s": round(data_s, 3)},
        "page_load_s": {"median": round(statistics.median(loads), 3), "all": [round(x, 3) for x in loads],
                        "until": "caviarView.ready, scene meshes loaded, first frame rendered",
                        "entities_drawn": n},
        "frame_rate": {"playing_10x": {k: round(v, 1) for k, v in fps.items()} | {"steps_advanced": s1 - s0}
                       | {"main_thread_ms": {k: round(v, 2) for k, v in parts.items() if v is not None}},
                       "idle": {k: round(v, 1) for k, v in idle.items()},
                       "how": "requestAnimationFrame callbacks and renders per second over the window, "
                              f"{args.entities} entities with trails, beams and 4 plots updating each frame"},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
