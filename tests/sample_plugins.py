"""Small plugins used by the tests."""

import dataclasses

import numpy as np

import caviar


class Counter(caviar.Plugin):
    """Publishes its step count and remembers what it received."""

    stateless = True  # what it publishes comes from the step alone

    @dataclasses.dataclass
    class Params:
        topic: str = "count"
        label: str = ""
        scale: float = 1.0

    def setup(self, ctx):
        self.ctx = ctx
        self.received = []

    def step(self, t, inbox):
        self.received.append([(m.topic, m.source, m.step) for m in inbox])
        return [(self.ctx.params.topic, {"step": self.ctx.step, "t": t, "label": self.ctx.params.label,
                                         "seen": len(inbox), "value": self.ctx.params.scale * self.ctx.step})]


class Noise(caviar.Plugin):
    """Random numbers from the module's seeded generator, as JSON and as an array."""

    stateless = True  # but for its random stream, which the host saves

    def step(self, t, inbox):
        x = self.ctx.rng.normal(size=4)
        yield "noise.json", {"x": x.tolist()}
        yield "noise.array", x.astype(np.complex64) * 1j


class Tables(caviar.Plugin):
    """A table a step (a polars DataFrame: Arrow on the wire): a row a draw, with a null."""

    stateless = True

    def step(self, t, inbox):
        import polars as pl

        x = self.ctx.rng.normal(size=3)
        yield "tables.draws", pl.DataFrame({"k": [0, 1, 2], "x": x, "name": ["a", None, "c"],
                                            "pair": np.stack([x, 2 * x], axis=1)})


class Tally(caviar.Plugin):
    """A running sum of the counts it receives and a random draw each step: state, an
    inbox and a random stream, all three needed to resume it exactly."""

    def setup(self, ctx):
        super().setup(ctx)
        self.total, self.seen = 0.0, 0

    def step(self, t, inbox):
        for m in inbox.on("count"):
            self.total += m.data["value"]
            self.seen += 1
        yield "tally", {"total": self.total, "seen": self.seen, "draw": float(self.ctx.rng.normal())}

    def state(self):
        return self.total, self.seen

    def restore(self, state):
        self.total, self.seen = state


class Crash(caviar.Plugin):
    @dataclasses.dataclass
    class Params:
        at_step: int = 3

    def step(self, t, inbox):
        if self.ctx.step == self.ctx.params.at_step:
            return 1 / 0
        return [("crash.alive", {"step": self.ctx.step})]


class Echo(caviar.Plugin):
    """Republishes what it receives, decoded and re-encoded, under echo.<topic>."""

    subscribe = ["noise.>"]

    def step(self, t, inbox):
        for m in inbox:
            yield caviar.Message("echo." + m.topic, m.data)


class WritesFile(caviar.Plugin):
    def step(self, t, inbox):
        path = self.ctx.artifact_dir / f"frame-{self.ctx.step:03d}.txt"
        path.write_text(f"t={t}")
        yield "files.frame", caviar.Artifact(path)


class Reader(caviar.Plugin):
    subscribe = ["files.frame"]

    def step(self, t, inbox):
        for m in inbox:
            yield "files.read", {"text": m.data.read_text(), "kind": m.kind}


class BadPayload(caviar.Plugin):
    def step(self, t, inbox):
        return [("bad.payload", {"value": object()})]


class NotAPlugin:
    pass


class FixedBeam(caviar.Plugin):
    """A beam selector that always picks the same pair for one UE."""

    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params:
        ue_id: str = "uav1"
        beam_pair: int = 0

    def step(self, t, inbox):
        if inbox.on("3D.mobility.positions"):
            yield "ai.beam.selection", {"UE_Id": self.ctx.params.ue_id, "beam_pair": self.ctx.params.beam_pair}


class ScriptedDetections(caviar.Plugin):
    """Throughput and detections as a detector would send them, on a fixed script."""

    def step(self, t, inbox):
        step = self.ctx.step
        yield "communications.throughput", {"UE_type": "UAV", "UE_Id": "uav1",
                                            "throughput": 80.0 if step >= 3 else 40.0}
        ground = {1: [(10.0, 10.0)], 2: [(12.0, 12.0)], 3: [(50.0, 10.0)]}.get(step, [])
        yield "ai.detections", {"UE_Id": "uav1", "count": len(ground),
                                "detections": [{"ground": {"x": x, "y": y}} for x, y in ground]}
        if step == 5:
            yield caviar.END_TOPIC, {"reason": "script"}


class Slow(caviar.Plugin):
    """Takes `seconds` of wall clock per step (to be killed mid-run)."""

    stateless = True

    @dataclasses.dataclass
    class Params:
        seconds: float = 0.1

    def step(self, t, inbox):
        import time

        time.sleep(self.ctx.params.seconds)
        return [("slow.tick", {"step": self.ctx.step})]


class SplitWork(caviar.Plugin):
    """Squares items 0..n-1; shard k of N takes the items i with i % N == k."""

    shardable = True

    @dataclasses.dataclass
    class Params:
        items: int = 10

    def step(self, t, inbox):
        import os

        mine = [i for i in range(self.ctx.params.items) if i % self.ctx.shards == self.ctx.shard]
        yield "work.part", {"step": self.ctx.step, "shard": self.ctx.shard, "squares": [i * i for i in mine]}
        yield "work.pid", os.getpid()


class Declared(caviar.Plugin):
    """Declares what it publishes (``caviar-core validate`` checks the wiring)."""

    publishes = ("declared.count",)

    def step(self, t, inbox):
        return [("declared.count", {"t": t})]


class DeclaredSink(caviar.Plugin):
    """Subscribes to what ``Declared`` publishes and to a topic nobody publishes."""

    subscribe = ["declared.*", "missing.topic"]
    publishes = ("sink.summary",)

    def step(self, t, inbox):
        return [("sink.summary", {"seen": len(inbox)})]


class BadPublishes(caviar.Plugin):
    publishes = ("a..b",)


class Checked(caviar.Plugin):
    """Checks its parameters with the ``check_params`` hook."""

    @dataclasses.dataclass
    class Params:
        limit: int = 1

    @classmethod
    def check_params(cls, params, config_dir):
        if params.limit < 0:
            raise caviar.ConfigError(f"expected a limit >= 0, got {params.limit}", "limit")


class Exits(caviar.Plugin):
    """Ends the whole process (no cleanup) at step `at_step`, or hangs there for good, or
    (`segfault`) crashes it in native code, or (`stall`) says so on stderr and stops the
    whole process (SIGSTOP: alive, silent); `hang_in = "setup"` or `"teardown"` hangs
    there instead."""

    @dataclasses.dataclass
    class Params:
        at_step: int = 5
        hang: bool = False
        segfault: bool = False
        stall: bool = False
        hang_in: str = ""

    def setup(self, ctx):
        import time

        super().setup(ctx)
        while ctx.params.hang_in == "setup":
            time.sleep(3600)

    def teardown(self):
        import time

        while self.ctx.params.hang_in == "teardown":
            time.sleep(3600)

    def step(self, t, inbox):
        import os
        import time

        if self.ctx.step == self.ctx.params.at_step:
            if self.ctx.params.hang:
                while True:
                    time.sleep(3600)
            if self.ctx.params.stall:
                import signal
                import sys

                print(f"exiter: stalling the whole process at step {self.ctx.step}", file=sys.stderr, flush=True)
                os.kill(os.getpid(), signal.SIGSTOP)
            if self.ctx.params.segfault:
                import ctypes
                import faulthandler

                faulthandler.disable()  # the crash itself, not Python's report of it
                ctypes.string_at(0)
            os._exit(3)
        return [("exits.alive", {"step": self.ctx.step})]


class LineMover(caviar.Plugin):
    """UEs moving along straight lines at constant speed: ``3D.mobility.positions``."""

    publishes = ("3D.mobility.positions",)
    stateless = True  # positions from t alone

    @dataclasses.dataclass
    class Params:
        ues: list = dataclasses.field(default_factory=list)  # [{id, type, start, end, speed}]

    def step(self, t, inbox):
        for ue in self.ctx.params.ues:
            a, b = np.asarray(ue["start"], float), np.asarray(ue["end"], float)
            length = float(np.linalg.norm(b - a))
            f = min(ue["speed"] * t / length, 1.0) if length > 0 else 1.0
            x, y, z = (float(v) for v in a + f * (b - a))
            yield "3D.mobility.positions", {"UE_type": ue.get("type", "car"), "UE_Id": ue["id"],
                                            "position": {"x": x, "y": y, "z": z}}


class ImageLayer(caviar.Plugin):
    """Writes ``layer.png`` (3 rows x 2 columns: red, blue, transparent from the top) and
    ``unnamed.png`` into the run directory and draws the first as a ``view.*`` image layer
    over ``extent`` at height ``z``; at step 1 another view.* topic names ``others``
    (files the view must refuse, for the server's tests)."""

    @dataclasses.dataclass
    class Params:
        extent: list = dataclasses.field(default_factory=lambda: [-300.0, 0.0, -50.0, 150.0])
        z: float = 200.0
        opacity: float = 1.0
        others: list = dataclasses.field(default_factory=list)

    def setup(self, ctx):
        from caviar.view.data import png_bytes

        self.ctx = ctx
        img = np.zeros((3, 2, 4), np.uint8)
        img[0] = [255, 0, 0, 255]
        img[1] = [0, 0, 255, 255]
        ctx.run_dir.mkdir(parents=True, exist_ok=True)
        (ctx.run_dir / "layer.png").write_bytes(png_bytes(img))
        (ctx.run_dir / "unnamed.png").write_bytes(png_bytes(img))

    def step(self, t, inbox):
        p = self.ctx.params
        if self.ctx.step == 0:
            yield "view.layer", {"images": [{"file": "layer.png", "extent": p.extent, "z": p.z,
                                             "opacity": p.opacity, "label": "test layer"}]}
        elif self.ctx.step == 1 and p.others:
            yield "view.others", {"images": [{"file": f, "extent": p.extent} for f in p.others]}


def synthetic_radio_map():
    """A radio map as ``best_server_map`` returns it (4 x 3 cells of 10 m, north at the
    last row), with one cell that no cell serves; and one site's 3 cells."""
    from caviar_plugins.network.cells import parse_sites

    cells = parse_sites([{"name": "A", "position": [15.0, 110.0, 30.0]}],
                        {"tx_power_dbm": 40.0, "carrier_hz": 3.5e9, "bandwidth_hz": 20e6, "array": [1, 1]})
    x, y = np.array([0.0, 10.0, 20.0, 30.0]), np.array([100.0, 110.0, 120.0])
    sinr = np.array([[-20.0, -10.0, 0.0, 5.0], [10.0, 15.0, np.nan, 25.0], [30.0, 35.0, 40.0, 55.0]])
    best = np.where(np.isnan(sinr), -1, np.arange(12).reshape(3, 4) % 3)
    gain = np.full((3, 3, 4), -90.0)
    return {"x": x, "y": y, "gain_db": gain, "rsrp_dbm": gain + 40.0, "best": best, "sinr_db": sinr}, cells


class RadioMapLayer(caviar.Plugin):
    """What the radio network does with its map: ``radio_map.save`` into the run directory
    at setup, ``radio_map.layer_message`` on ``view.radio_map`` at the first step."""

    def setup(self, ctx):
        from caviar_plugins.network import radio_map

        self.ctx = ctx
        self.result, cells = synthetic_radio_map()
        self.files = radio_map.save(self.result, cells, ctx.run_dir)

    def step(self, t, inbox):
        from caviar_plugins.network import radio_map

        if self.ctx.step == 0:
            layer = self.files[-1].relative_to(self.ctx.run_dir).as_posix()
            yield "view.radio_map", radio_map.layer_message(self.result, layer, height_m=1.5)


class WallClock(caviar.Plugin):
    """Publishes the wall clock (``time.monotonic()``) at the start of each step on
    ``clock.wall``, then takes ``seconds`` of wall clock (for the pacing tests)."""

    @dataclasses.dataclass
    class Params:
        seconds: float = 0.0

    def step(self, t, inbox):
        import time

        start = time.monotonic()
        if self.ctx.params.seconds:
            time.sleep(self.ctx.params.seconds)
        return [("clock.wall", {"step": self.ctx.step, "t": t, "wall": start})]


class Status(caviar.Plugin):
    """Says how far it got on caviar.status every step; at ``bad_at`` tries another
    reserved topic."""

    stateless = True
    publishes = (caviar.STATUS_TOPIC, "caviar.other")

    @dataclasses.dataclass
    class Params:
        bad_at: int = -1

    def setup(self, ctx):
        self.ctx = ctx

    def step(self, t, inbox):
        if self.ctx.step == self.ctx.params.bad_at:
            yield "caviar.other", "x"
        yield caviar.STATUS_TOPIC, f"{self.ctx.step + 1} steps\nsaid"


class CarAt(caviar.Plugin):
    """A SUMO-like car (``dimensions``, ``heading``) at x = ``xs[step]`` on the x axis."""

    publishes = ("3D.mobility.positions",)
    stateless = True  # its position from the step alone

    @dataclasses.dataclass
    class Params:
        xs: list = dataclasses.field(default_factory=list)
        height: float = 1.5

    def step(self, t, inbox):
        p = self.ctx.params
        x = float(p.xs[min(self.ctx.step, len(p.xs) - 1)])
        yield "3D.mobility.positions", {"UE_type": "passenger", "UE_Id": "car1",
                                        "position": {"x": x, "y": 0.0, "z": 0.0}, "heading": 0.0,
                                        "dimensions": {"length": 4.5, "width": 1.8, "height": p.height}}


class Payloads(caviar.Plugin):
    """Publishes ``bytes`` of ``size`` on ``payload.<UE>`` at the listed steps (a message
    the network carries)."""

    publishes = ("payload.*",)
    stateless = True

    @dataclasses.dataclass
    class Params:
        ue: str = "u1"
        size: int = 1000
        steps: list[int] = dataclasses.field(default_factory=lambda: [0])

    def step(self, t, inbox):
        p = self.ctx.params
        if self.ctx.step in p.steps:
            yield f"payload.{p.ue}", bytes([self.ctx.step % 256]) * p.size


class OneDetection(caviar.Plugin):
    """A person seen on the ground at step ``at`` (none at the others): ``ai.detections``."""

    publishes = ("ai.detections",)
    stateless = True

    @dataclasses.dataclass
    class Params:
        at: int = 2
        ue: str = "uav1"

    def step(self, t, inbox):
        p = self.ctx.params
        found = [{"ground": {"x": 1.0, "y": 2.0}}] if self.ctx.step == p.at else []
        yield "ai.detections", {"UE_Id": p.ue, "count": len(found), "detections": found}


class Leaves(caviar.Plugin):
    """UE ``ue`` leaves the scene at step ``at``: ``3D.mobility.arrived``."""

    publishes = ("3D.mobility.arrived",)
    stateless = True

    @dataclasses.dataclass
    class Params:
        ue: str = "u1"
        at: int = 1

    def step(self, t, inbox):
        if self.ctx.step == self.ctx.params.at:
            yield "3D.mobility.arrived", {"UE_type": "car", "UE_Id": self.ctx.params.ue}
