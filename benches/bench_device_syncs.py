"""Where the radio network's step would wait for a GPU, counted on the CPU (issue #53).

On a GPU, a torch operation whose result the host must read (``.item()``, ``.tolist()``,
``.cpu()``, ``bool(t)``, ``nonzero``, a boolean-mask index, whose size is data) waits for
every kernel queued before it. The H200 ran the network at 21 cells x 100 UEs at T_p/T_v 2.16
against 1.05 the session before; this counts, per step, the operations of the ``radio-network``
plugin that read a device value, by name, and all its torch calls (each one launch or more on a
GPU), with a ``TorchFunctionMode`` (torch's own hook,
real plugin, compiled link level as on the GPU; what runs inside a compiled region is not
seen, and needs no sync). ``--against REV`` runs a git revision's plugins the same way (a
worktree under /tmp) in the same run, for the ratio.

    .venv/bin/python benches/bench_device_syncs.py [--ues 100] [--steps 4] [--against 80c5581]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent

READS = {"item", "tolist", "cpu", "__bool__", "__int__", "__float__", "__index__", "nonzero", "masked_select",
         "unique", "argwhere", "repeat_interleave"}
"""Tensor methods and torch functions whose result the host must read, or whose result's size
is data (``.numpy()`` is not counted: on a GPU it follows ``.cpu()``)."""


def count(n_ue: int, steps: int) -> dict:
    import numpy as np
    import torch
    from torch.overrides import TorchFunctionMode

    sys.path.insert(0, str(ROOT / "benches"))
    import bench_network as bn
    from caviar._host import Hosted, check_params
    from caviar.plugin import Inbox, Message
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.schema import position_payload

    class Reads(TorchFunctionMode):
        def __init__(self):
            super().__init__()
            self.calls: collections.Counter = collections.Counter()

        def __torch_function__(self, func, types, args=(), kwargs=None):
            if torch.compiler.is_compiling():  # (what a compiled region runs is its own kernels: not counted)
                return func(*args, **(kwargs or {}))
            name = getattr(func, "__name__", str(func))
            self.calls[" all torch calls"] += 1  # (each a launch or more on a GPU, outside compiled code)
            if name in READS:
                self.calls[name] += 1
            elif name == "__getitem__" and len(args) > 1 and isinstance(args[1], torch.Tensor) and \
                    args[1].dtype == torch.bool:
                self.calls["getitem[bool mask]"] += 1
            return func(*args, **(kwargs or {}))

    kinds, pos0, vel = bn.ues(np.random.default_rng(7), n_ue)
    params = {"sites": bn.sites(), "carrier_hz": 3.5e9, "bandwidth_hz": 20e6, "tx_power_dbm": 43.0, "array": [4, 4],
              "subcarrier_spacing_hz": bn.SCS, "harq_processes": 8, "subbands": 8, "compile": True,
              "channel": "ray-traced", "interference": "scheduled", "antenna_height_m": 0.0,
              "scene": str(bn.SCENE), "raytracing": {"max_depth": 2, "samples_per_src": 2000},
              "evolution": {"refresh_s": 100.0},
              "beams": {"horizontal": 4, "vertical": 1}, "uplink": {}}
    import tempfile

    hosted = Hosted("net", RadioNetwork(), check_params(RadioNetwork, params))
    per_step = []
    with tempfile.TemporaryDirectory() as run_dir:
        hosted.setup(seed=1, ts=bn.TS, steps=None, every=1, offset=0, run_dir=run_dir, config_dir=str(ROOT))
        for k in range(steps + 1):
            t = k * bn.TS
            pos = pos0 + vel * t
            inbox = Inbox([Message("3D.mobility.positions", position_payload(f"{kinds[u]}{u}", pos[u], kinds[u]),
                                   step=k, time=t) for u in range(len(pos))])
            hosted.ctx.step = k
            if k == 0:  # (the first step traces and compiles: not counted)
                list(hosted.plugin.step(t, inbox) or ())
                continue
            mode = Reads()
            with mode:  # (a step is a generator: consumed here)
                messages = list(hosted.plugin.step(t, inbox) or ())
            assert messages, "the step published nothing"
            per_step.append(mode.calls)
    total: collections.Counter = sum(per_step, collections.Counter())
    calls = total.pop(" all torch calls")
    return {"reads_per_step": round(sum(total.values()) / len(per_step), 1),
            "by_name_per_step": {k: round(v / len(per_step), 1) for k, v in total.most_common()},
            "torch_calls_per_step": round(calls / len(per_step), 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ues", type=int, default=100)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--against", help="a git revision whose plugins run the same count")
    ap.add_argument("--out", type=pathlib.Path, default=ROOT / "docs/results/device-syncs.json")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(count(args.ues, args.steps)))
        return 0
    from bench_common import machine

    def child(plugins: pathlib.Path | None) -> dict:
        env = dict(os.environ)
        if plugins is not None:
            env["PYTHONPATH"] = f"{plugins}{os.pathsep}{env.get('PYTHONPATH', '')}"
        p = subprocess.run([sys.executable, __file__, "--child", "--ues", str(args.ues), "--steps", str(args.steps)],
                           capture_output=True, text=True, env=env, cwd=ROOT)
        if p.returncode != 0:
            raise SystemExit(p.stderr[-3000:])
        return json.loads(p.stdout.strip().splitlines()[-1])

    result: dict = {"cells": 21, "ues": args.ues, "steps_counted": args.steps, "machine": machine(),
                    "head": child(None)}
    if args.against:
        tree = pathlib.Path(f"/tmp/caviar-{args.against}")
        if not tree.exists():
            subprocess.run(["git", "worktree", "add", "--detach", str(tree), args.against], cwd=ROOT, check=True,
                           capture_output=True)
        result[args.against] = child(tree / "plugins")
    print(json.dumps(result, indent=2))
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
