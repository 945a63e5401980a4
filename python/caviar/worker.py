"""``caviar worker``: runs one module of a run in this process, over NATS.

    caviar worker --nats nats://gpu-box:4222 --run sar-004 --module radio

The worker says hello to the run's core, receives its plugin and parameters, loads
the plugin, and then answers the core's setup, step and teardown requests until the
run ends. It beats every second so that the core notices a worker that hangs or
dies. The plugin code is the same as in-process (``caviar._host.Hosted``); the wire
format is in docs/nats-protocol.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import ssl
import struct
import sys
import threading
import time

from caviar._gpu import open_sampler
from caviar._host import format_exception, load_plugin
from caviar.errors import ConfigError

PROTOCOL = 1
HEARTBEAT_S = 1.0


def pack_frame(header: dict, bodies: list[bytes]) -> bytes:
    """4-byte little-endian header length, JSON header, bodies back to back."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return b"".join([struct.pack("<I", len(head)), head, *bodies])


def unpack_frame(buf: bytes) -> tuple[dict, memoryview]:
    (n,) = struct.unpack_from("<I", buf)
    return json.loads(buf[4:4 + n]), memoryview(buf)[4 + n:]


def decode_request(buf: bytes) -> tuple[dict, list[tuple]]:
    """The step request and its messages as ``_host`` tuples."""
    req, rest = unpack_frame(buf)
    if req.get("protocol") != PROTOCOL:
        raise ValueError(f"protocol {req.get('protocol')} requested, this worker speaks {PROTOCOL}")
    raw, pos = [], 0
    for m in req["messages"]:
        body = bytes(rest[pos:pos + m["len"]])
        pos += m["len"]
        kind = m["kind"]
        if kind in ("json", "artifact"):
            body = body.decode()
        raw.append((m.get("step", req["step"]), m.get("time", req["time"]), m["topic"], m.get("source", ""),
                    kind, body, m.get("meta")))
    return req, raw


def encode_reply(out: list[tuple], wall_s: float, cpu_s: float, gpu: tuple[float, float] | None = None) -> bytes:
    messages, bodies = [], []
    for topic, kind, body, meta in out:
        b = body.encode() if isinstance(body, str) else bytes(body)
        m = {"topic": topic, "kind": kind, "len": len(b)}
        if meta is not None:
            m["meta"] = meta
        messages.append(m)
        bodies.append(b)
    header = {"ok": True, "messages": messages, "wall_s": wall_s, "cpu_s": cpu_s, "rss_mib": resident_mib()}
    if gpu is not None:
        header["gpu_util_pct"], header["gpu_mem_mib"] = gpu
    return pack_frame(header, bodies)


def error_reply(exc: BaseException) -> dict:
    """The failure as the core reports it: "Type: message" and the traceback, or for a
    configuration error its message and the key under ``modules.NAME``."""
    if isinstance(exc, ConfigError):
        return {"ok": False, "error": {"message": exc.message, "key": exc.key, "trace": None}}
    return {"ok": False, "error": {"message": f"{type(exc).__name__}: {exc}", "trace": format_exception(exc)}}


_PAGE_MIB = os.sysconf("SC_PAGE_SIZE") / 2**20 if hasattr(os, "sysconf") else float("nan")


def resident_mib() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE_MIB
    except OSError:
        return float("nan")


class Worker:
    """Plugin calls (load, setup, step, teardown) run on the event loop's thread: no
    thread hop per step (the barrier's latency) and one thread for libraries with
    per-thread state such as Dr.Jit. The heartbeat has a thread and a connection of
    its own, so it keeps beating through long steps."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.run, self.module = args.run, args.module
        self.id = args.worker_id or f"{args.module}-{socket.gethostname()}-{os.getpid()}"
        self.prefix = f"caviar.{self.run}"
        self.hosted = None
        self.spec: dict = {}
        self.done = asyncio.Event()
        self.gpu = open_sampler()
        self.exit_code = 0

    def log(self, text: str) -> None:
        print(f"caviar worker {self.id}: {text}", file=sys.stderr, flush=True)

    async def connect(self):
        import nats

        a = self.args
        tls = None
        if a.tls_ca or a.tls_cert:
            tls = ssl.create_default_context(cafile=a.tls_ca)
            if a.tls_cert:
                tls.load_cert_chain(a.tls_cert, a.tls_key)
        options = dict(servers=a.nats.split(","), name=f"caviar-worker {self.id}", tls=tls,
                       user_credentials=a.creds, token=os.environ.get("NATS_TOKEN"),
                       user=os.environ.get("NATS_USER"), password=os.environ.get("NATS_PASSWORD"),
                       max_reconnect_attempts=a.reconnect_attempts, reconnect_time_wait=1,
                       closed_cb=self._closed, disconnected_cb=self._disconnected,
                       reconnected_cb=self._reconnected)
        self.options = {k: v for k, v in options.items() if v is not None}
        self.nc = await nats.connect(**self.options)

    async def _closed(self):
        if not self.done.is_set():
            self.log("connection to the NATS server closed; leaving")
            self.exit_code = 1
            self.done.set()

    async def _disconnected(self):
        if not self.done.is_set():
            self.log("disconnected from the NATS server; retrying")

    async def _reconnected(self):
        self.log("reconnected")

    async def hello(self) -> dict:
        """Asks the core for the module; waits for the core to come up (--wait seconds)."""
        import nats.errors

        body = json.dumps({"protocol": PROTOCOL, "module": self.module, "worker": self.id,
                           "host": socket.gethostname(), "pid": os.getpid()}).encode()
        deadline = time.monotonic() + self.args.wait
        while True:
            try:
                reply = await self.nc.request(f"{self.prefix}.hello", body, timeout=5)
                return json.loads(reply.data)
            except (nats.errors.NoRespondersError, nats.errors.TimeoutError):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no core answered on {self.prefix}.hello within {self.args.wait:.0f} s "
                                       f"(is run '{self.run}' started?)") from None
                await asyncio.sleep(0.5)

    def _load(self):
        s = self.spec
        hosted, subscribe = load_plugin(self.module, s["plugin"], json.dumps(s["params"]), s["config_dir"])
        if s.get("shards", 1) > 1 and not type(hosted.plugin).shardable:
            raise ConfigError(f"{type(hosted.plugin).__name__} cannot split a step into shards "
                              f"(it does not declare shardable = True)", "shards")
        return hosted, subscribe

    async def serve(self) -> int:
        await self.connect()
        try:
            self.spec = await self.hello()
        except TimeoutError as e:
            self.log(str(e))
            return 1
        if not self.spec.get("ok"):
            self.log(f"the core refused this worker: {self.spec.get('error')}")
            return 2
        loaded = f"{self.prefix}.loaded"
        try:
            self.hosted, subscribe = self._load()
        except Exception as e:  # the core reports it as a configuration error
            await self.nc.publish(loaded, json.dumps({"worker": self.id, **error_reply(e)}).encode())
            await self.nc.flush()
            self.log(f"cannot load plugin {self.spec['plugin']!r}: {e}")
            return 2
        me = f"{self.prefix}.{self.module}.{self.id}"
        await self.nc.subscribe(f"{me}.setup", cb=self.on_setup)
        await self.nc.subscribe(f"{me}.teardown", cb=self.on_teardown)
        await self.nc.subscribe(f"{self.prefix}.stop", cb=self.on_stop)
        await self.nc.publish(loaded, json.dumps({"worker": self.id, "subscribe": subscribe}).encode())
        await self.nc.flush()
        stop_beating = threading.Event()
        beat = threading.Thread(target=self.heartbeat, args=(stop_beating,), name="heartbeat", daemon=True)
        beat.start()
        await self.done.wait()
        stop_beating.set()
        if not self.nc.is_closed:
            await self.nc.drain()
        beat.join(timeout=3)
        return self.exit_code

    def heartbeat(self, stop: threading.Event) -> None:
        """Beats every second from its own thread and connection, also while a long
        step keeps the main loop busy (Python code yields the interpreter lock every
        few milliseconds; native code such as Dr.Jit releases it)."""
        import nats

        async def beat():
            nc = await nats.connect(**dict(self.options, name=f"caviar-worker {self.id} heartbeat",
                                           closed_cb=None, disconnected_cb=None, reconnected_cb=None))
            body = json.dumps({"worker": self.id}).encode()
            while not stop.is_set():
                try:
                    await nc.publish(f"{self.prefix}.heartbeat", body)
                    await nc.flush(timeout=HEARTBEAT_S)
                except Exception as e:  # reconnecting: the core times us out if it lasts
                    self.log(f"heartbeat not sent: {e}")
                await asyncio.sleep(HEARTBEAT_S)
            await nc.close()

        asyncio.run(beat())

    async def on_setup(self, msg):
        s, c = self.spec, json.loads(msg.data)
        try:
            self.hosted.setup(c["seed"], c["ts"], c["steps"], c["every"], c["offset"],
                              s["run_dir"], s["config_dir"], s.get("shards", 1))
        except Exception as e:
            await msg.respond(json.dumps(error_reply(e)).encode())
            return
        # Steps come through the module's queue group: several workers share them.
        await self.nc.subscribe(f"{self.prefix}.{self.module}.step", queue=self.module, cb=self.on_step)
        await self.nc.flush()  # subscribed on the server before the core's first step
        await msg.respond(b'{"ok":true}')

    def _step(self, req: dict, raw: list) -> bytes:
        t0, c0 = time.perf_counter(), time.process_time()
        out = self.hosted.step(req["step"], req["time"], raw, req.get("shard", 0))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return encode_reply(out, wall, cpu, self.gpu.sample() if self.gpu else None)

    async def on_step(self, msg):
        try:
            req, raw = decode_request(msg.data)
            reply = self._step(req, raw)
        except Exception as e:
            reply = pack_frame(error_reply(e), [])
        await msg.respond(reply)

    async def on_teardown(self, msg):
        try:
            self.hosted.teardown()
            reply = b'{"ok":true}'
        except Exception as e:
            reply = json.dumps(error_reply(e)).encode()
        await msg.respond(reply)
        await self.nc.flush()
        self.done.set()

    async def on_stop(self, msg):
        self.done.set()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="caviar worker", description=__doc__.split("\n\n")[0])
    p.add_argument("--nats", required=True, help="NATS server URL(s), comma-separated")
    p.add_argument("--run", required=True, help="run id (the core prints it; default: the run directory's name)")
    p.add_argument("--module", required=True, help="the [modules.NAME] this worker runs")
    p.add_argument("--worker-id", help="unique name of this worker (default: MODULE-HOST-PID)")
    p.add_argument("--wait", type=float, default=120.0, help="seconds to wait for the core (default 120)")
    p.add_argument("--reconnect-attempts", type=int, default=10,
                   help="reconnection attempts, one per second, before giving up (default 10)")
    p.add_argument("--creds", help="NATS credentials file")
    p.add_argument("--tls-ca", help="CA certificates to trust")
    p.add_argument("--tls-cert", help="client certificate")
    p.add_argument("--tls-key", help="client key")
    args = p.parse_args(argv)
    if bool(args.tls_cert) != bool(args.tls_key):
        p.error("--tls-cert and --tls-key go together")
    # NATS_TOKEN / NATS_USER / NATS_PASSWORD come from the environment: not on the command line.
    try:
        return asyncio.run(Worker(args).serve())
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
