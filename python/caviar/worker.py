"""``caviar worker``: runs one module of a run in this process, over NATS.

    caviar worker --nats nats://gpu-box:4222 --run sar-004 --module radio

The worker says hello to the run's core, receives its plugin and parameters, loads
the plugin, and then answers the core's setup, step and teardown requests until the
run ends. It beats every second so that the core notices a worker that hangs or
dies. The plugin code is the same as in-process (``caviar._host.Hosted``); the wire
format is in docs/nats-protocol.md and its frames are encoded and decoded by the core
(``caviar._core.decode_request``, ``encode_reply``, ``encode_failure``).

Every frame of the core is authenticated with the run key (``CAVIAR_RUN_KEY``, or the
file named by ``CAVIAR_RUN_KEY_FILE``) and every answer sealed with it, by the core's
own code (``caviar._core.Guard``); frames that fail, repeat a sequence number or carry
an unexpected step are refused, logged and counted (reported in the heartbeat).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import pathlib
import socket
import ssl
import sys
import threading
import time
from collections.abc import MutableMapping
from typing import TYPE_CHECKING

from caviar import _core
from caviar._gpu import open_sampler
from caviar._host import Hosted, OutgoingTuple, format_exception, load_plugin
from caviar.errors import ConfigError

if TYPE_CHECKING:
    from nats.aio.msg import Msg

PROTOCOL = _core.PROTOCOL
HEARTBEAT_S = 1.0


def encode_reply(out: list[OutgoingTuple], wall_s: float, cpu_s: float,
                 gpu: tuple[float, float] | None = None) -> bytes:
    """A step reply frame (the core's own encoder, ``caviar._core.encode_reply``)."""
    return _core.encode_reply(out, wall_s, cpu_s, rss_mib=_core.resident_mib(), gpu=gpu)


def error_reply(exc: BaseException) -> dict:
    """The failure as the core reports it: "Type: message" and the traceback, or for a
    configuration error its message and the key under ``modules.NAME``."""
    if isinstance(exc, ConfigError):
        return {"ok": False, "error": {"message": exc.message, "key": exc.key, "trace": None}}
    return {"ok": False, "error": {"message": f"{type(exc).__name__}: {exc}", "trace": format_exception(exc)}}


def key_env(env: MutableMapping[str, str]) -> None:
    """With ``CAVIAR_RUN_KEY_FILE`` naming a run key file written by the core (lines
    ``NAME=value``), takes the NATS credentials in it that the environment lacks."""
    path = env.get("CAVIAR_RUN_KEY_FILE")
    if not path or "CAVIAR_RUN_KEY" in env:
        return
    try:
        text = pathlib.Path(path).read_text()
    except OSError:
        return  # the core's Guard says what is missing
    for line in text.splitlines():
        name, sep, value = line.strip().partition("=")
        if sep and name in ("NATS_USER", "NATS_PASSWORD", "NATS_TOKEN"):
            env.setdefault(name, value)


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
        self.hosted: Hosted | None = None
        self.spec: dict = {}
        self.done = asyncio.Event()
        self.gpu = open_sampler()
        self.exit_code = 0
        key_env(os.environ)  # NATS credentials of a run key file, before connecting
        self.guard = _core.Guard(self.run)

    def log(self, text: str) -> None:
        print(f"caviar worker {self.id}: {text}", file=sys.stderr, flush=True)

    def _open(self, msg: Msg) -> bytes | None:
        """The body of a frame of the core, or None (logged, counted) when it is refused."""
        try:
            return self.guard.open(msg.subject, msg.data)
        except ValueError as e:
            self.log(f"security: refused {e} ({self.guard.rejected} refused so far)")
            return None

    def _refuse(self, why: str) -> None:
        self.guard.refuse()
        self.log(f"security: refused {why} ({self.guard.rejected} refused so far)")

    async def _respond(self, msg: Msg, body: bytes) -> None:
        """Answers the core's request, sealed for its reply subject."""
        await self.nc.publish(msg.reply, self.guard.seal(msg.reply, body))

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
        subject = f"{self.prefix}.hello"
        while True:
            try:
                reply = await self.nc.request(subject, self.guard.seal(subject, body), timeout=5)
                answer = self._open(reply)
                if answer is not None:
                    return json.loads(answer)
                raise nats.errors.TimeoutError  # someone without the key answered: ask again
            except (nats.errors.NoRespondersError, nats.errors.TimeoutError):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no core answered on {self.prefix}.hello within {self.args.wait:.0f} s "
                                       f"(is run '{self.run}' started?)") from None
                await asyncio.sleep(0.5)

    def _plugin(self) -> Hosted:
        """The loaded plugin: setup, step and teardown requests are subscribed to only
        once it is loaded."""
        assert self.hosted is not None, "plugin requests arrive only after the plugin is loaded"
        return self.hosted

    def _load(self) -> tuple[Hosted, list[str], list[str], list[str], list[tuple[str, str]]]:
        s = self.spec
        hosted, subscribe, publishes, optional, required = load_plugin(
            self.module, s["plugin"], json.dumps(s["params"]), s["config_dir"])
        if s.get("shards", 1) > 1 and not type(hosted.plugin).shardable:
            raise ConfigError(f"{type(hosted.plugin).__name__} cannot split a step into shards "
                              f"(it does not declare shardable = True)", "shards")
        return hosted, subscribe, publishes, optional, required

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
            self.hosted, subscribe, publishes, optional, required = self._load()
        except Exception as e:  # the core reports it as a configuration error
            await self.nc.publish(loaded, self.guard.seal(loaded, json.dumps({"worker": self.id,
                                                                                **error_reply(e)}).encode()))
            await self.nc.flush()
            self.log(f"cannot load plugin {self.spec['plugin']!r}: {e}")
            return 2
        me = f"{self.prefix}.{self.module}.{self.id}"
        await self.nc.subscribe(f"{me}.setup", cb=self.on_setup)
        await self.nc.subscribe(f"{me}.teardown", cb=self.on_teardown)
        await self.nc.subscribe(f"{me}.state", cb=self.on_state)
        await self.nc.subscribe(f"{me}.resume", cb=self.on_resume)
        await self.nc.subscribe(f"{self.prefix}.stop", cb=self.on_stop)
        await self.nc.publish(loaded, self.guard.seal(loaded, json.dumps(
            {"worker": self.id, "subscribe": subscribe, "publishes": publishes, "optional": optional,
             "required": required}).encode()))
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
            subject = f"{self.prefix}.heartbeat"
            while not stop.is_set():
                try:
                    body = json.dumps({"worker": self.id, "rejected": self.guard.rejected}).encode()
                    await nc.publish(subject, self.guard.seal(subject, body))
                    # nats-py annotates timeout as int; it is seconds for asyncio.wait_for, a float is fine.
                    await nc.flush(timeout=HEARTBEAT_S)  # type: ignore[arg-type]
                except Exception as e:  # reconnecting: the core times us out if it lasts
                    self.log(f"heartbeat not sent: {e}")
                await asyncio.sleep(HEARTBEAT_S)
            await nc.close()

        asyncio.run(beat())

    async def on_setup(self, msg: Msg) -> None:
        data = self._open(msg)
        if data is None:
            return
        if not msg.reply:
            self._refuse("a setup without a reply subject")
            return
        s, c = self.spec, json.loads(data)
        self.guard.schedule(c["every"], c["offset"], c["steps"], s.get("shards", 1), bool(c.get("exclusive")))
        try:
            self._plugin().setup(c["seed"], c["ts"], c["steps"], c["every"], c["offset"],
                              s["run_dir"], s["config_dir"], s.get("shards", 1))
        except Exception as e:
            await self._respond(msg, json.dumps(error_reply(e)).encode())
            return
        # Steps come through the module's queue group: several workers share them.
        await self.nc.subscribe(f"{self.prefix}.{self.module}.step", queue=self.module, cb=self.on_step)
        await self.nc.flush()  # subscribed on the server before the core's first step
        await self._respond(msg, b'{"ok":true}')

    def _step(self, req: _core.StepRequest) -> bytes:
        t0, c0 = time.perf_counter(), time.process_time()
        out = self._plugin().step(req.step, req.time, req.messages, req.shard)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return encode_reply(out, wall, cpu, self.gpu.sample() if self.gpu else None)

    async def on_step(self, msg: Msg) -> None:
        data = self._open(msg)
        if data is None:
            return
        try:
            req = _core.decode_request(data)
        except Exception as e:
            await self._respond(msg, _core.encode_failure(**error_reply(e)["error"]))
            return
        try:
            self.guard.accept_step(req.step, req.shard)
        except ValueError as e:
            self.log(f"security: refused {e} ({self.guard.rejected} refused so far)")
            return
        try:
            reply = self._step(req)
        except Exception as e:
            reply = _core.encode_failure(**error_reply(e)["error"])
        await self._respond(msg, reply)

    async def on_teardown(self, msg: Msg) -> None:
        if self._open(msg) is None:
            return
        if not msg.reply:
            self._refuse("a teardown without a reply subject")
            return
        result: dict
        try:
            self._plugin().teardown()
            result = {"ok": True}
        except Exception as e:
            result = error_reply(e)
        result["rejected"] = self.guard.rejected
        await self._respond(msg, json.dumps(result).encode())
        await self.nc.flush()
        self.done.set()

    async def on_state(self, msg: Msg) -> None:
        """A checkpoint: the plugin's state (hex), "stateless", or why it has none."""
        if self._open(msg) is None:
            return
        if not msg.reply:
            self._refuse("a state request without a reply subject")
            return
        result: dict
        try:
            kind, value = self._plugin().state()
            result = {"ok": True, "kind": kind, "hex": value.hex() if kind == "saved" else None,
                      "why": value if kind == "unsupported" else None}
        except Exception as e:
            result = error_reply(e)
        await self._respond(msg, json.dumps(result).encode())

    async def on_resume(self, msg: Msg) -> None:
        """A resumed run: the state to restore (if any), and the step it goes on at."""
        data = self._open(msg)
        if data is None:
            return
        if not msg.reply:
            self._refuse("a resume without a reply subject")
            return
        c = json.loads(data)
        result: dict
        try:
            if c.get("hex") is not None:
                self._plugin().restore(bytes.fromhex(c["hex"]))
            self.guard.resume_at(int(c["next_step"]))
            result = {"ok": True}
        except Exception as e:
            result = error_reply(e)
        await self._respond(msg, json.dumps(result).encode())

    async def on_stop(self, msg: Msg) -> None:
        if self._open(msg) is not None:
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
    # NATS_TOKEN / NATS_USER / NATS_PASSWORD and the run key come from the environment:
    # not on the command line, where every user of the machine can read them.
    try:
        worker = Worker(args)
    except ValueError as e:
        print(f"caviar worker: {e}", file=sys.stderr)
        return 2
    try:
        return asyncio.run(worker.serve())
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
