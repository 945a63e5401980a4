"""The radio network's step has no per-UE host work (issue #53, part 4): at 21 cells it makes
the same Python calls with 1,000 UEs as with 100, apart from reading each UE's position and
writing each UE's reports (a message each, in and out). Measurements, mobility, the SSB beams,
the downlink and uplink SINRs, the link levels' columns and the traffic queues are array work:
a Python loop over UEs coming back in any of them fails here (its calls grow with the UEs), not
in a timing."""

from __future__ import annotations

import collections
import gc
import sys

import numpy as np
import pytest

pytest.importorskip("sionna.sys")

from caviar._host import Hosted, check_params  # noqa: E402
from caviar.plugin import Inbox, Message  # noqa: E402
from caviar_plugins.network.plugin import RadioNetwork  # noqa: E402
from caviar_plugins.schema import position_payload  # noqa: E402

TS = 0.004
"""A step of 8 slots of 0.5 ms: one group of the 8 HARQ processes per link level."""
PER_MESSAGE = {
    # reading the positions (one message a UE): the payload, the inbox's topic match, the table
    ("plugin.py", "data"), ("plugin.py", "decode"), ("topics.py", "matches"), ("ues.py", "__contains__"),
    ("ues.py", "column"),
    # writing every UE's communications.throughput and network.ue (the step's generator resumed a message)
    ("plugin.py", "step"), ("ues.py", "ue_reports"), ("ues.py", "extras"),
}
"""Functions called once or more per UE because a UE is a message in and two out."""


def _sites() -> list[dict]:
    """7 sites of 3 sectors, a centre and a ring at 280 m (benches/bench_network.py's)."""
    out = [{"name": "s0", "position": [0.0, 0.0, 35.0]}]
    out += [{"name": f"s{k + 1}", "position": [280 * np.cos(np.radians(60 * k + 30)),
                                             280 * np.sin(np.radians(60 * k + 30)), 35.0]} for k in range(6)]
    for s in out:
        s["azimuths_deg"], s["downtilt_deg"] = [30.0, 150.0, 270.0], 6.0
    return out


def _calls(n_ue: int, tmp_path, ue_reports: str = "per-ue") -> collections.Counter:
    """The Python calls of the third step of a network of 21 cells and ``n_ue`` UEs (moving),
    by (file, function), its reports ``ue_reports``."""
    params = {"sites": _sites(), "carrier_hz": 3.5e9, "bandwidth_hz": 20e6, "tx_power_dbm": 43.0, "array": [4, 4],
              "subcarrier_spacing_hz": 30e3, "harq_processes": 8, "subbands": 8, "channel": "free-space",
              "interference": "scheduled", "beams": {"horizontal": 4}, "uplink": {}, "device": "cpu",
              "traffic": {"downlink": "ftp3", "uplink": "full-buffer", "ftp": {"arrival_rate_hz": 1e-3}},
              "ue_reports": ue_reports}
    hosted = Hosted("net", RadioNetwork(), check_params(RadioNetwork, params))
    rng = np.random.default_rng(3)
    pos = np.column_stack([rng.uniform(-380, 380, n_ue), rng.uniform(-380, 380, n_ue), np.full(n_ue, 1.5)])
    vel = np.column_stack([rng.uniform(-10, 10, (n_ue, 2)), np.zeros(n_ue)])
    run_dir = tmp_path / f"run{n_ue}-{ue_reports}"
    run_dir.mkdir()
    hosted.setup(seed=1, ts=TS, steps=None, every=1, offset=0, run_dir=str(run_dir), config_dir=str(tmp_path))
    assert hosted.ctx is not None
    net = hosted.plugin
    counts: collections.Counter = collections.Counter()

    def count(frame, event, arg):
        if event == "call" and frame.f_code.co_name != "gc_callback":  # a collector's hook, not the step
            code = frame.f_code
            counts[(code.co_filename.rsplit("/", 1)[-1], code.co_name)] += 1

    for k in range(3):
        hosted.ctx.step = k
        box = Inbox([Message("3D.mobility.positions", position_payload(f"car{u}", pos[u] + vel[u] * k * TS, "car"),
                             step=k, time=k * TS) for u in range(n_ue)])
        if k == 2:
            # Another test's garbage (with pytest-xdist, torch.compile's weak-keyed caches) collected in
            # the middle of this step runs its weakref callbacks here: collect it first, and let no
            # cycle collection start during the counted step (objects the step itself frees still count).
            gc.collect()
            gc.disable()
            sys.setprofile(count)
        try:
            out = list(net.step(k * TS, box) or ())
        finally:
            sys.setprofile(None)
            gc.enable()
        reported = [v for topic, v in out if topic in ("network.ue", "network.ues")]
        assert (len(reported) if ue_reports == "per-ue" else reported[0].height) == n_ue
    hosted.teardown()  # (what set-up froze for the collector, given back)
    return counts


@pytest.mark.parametrize("ue_reports, allowed", [("per-ue", 20), ("table", 8)])
def test_a_step_makes_the_same_python_calls_for_1000_ues_as_for_100(tmp_path, ue_reports, allowed):
    """Per UE: with per-UE reports, a message in and two out; with the table, a message in and
    the paper's throughput out (``allowed``: calls a UE at most, for those)."""
    few, many = _calls(100, tmp_path, ue_reports), _calls(1000, tmp_path, ue_reports)
    grown = {f: (few[f], n) for f, n in many.items() if f not in PER_MESSAGE and n > 2 * few[f] + 10}
    assert not grown, f"per-UE Python calls in the network's step (calls at 100 and 1,000 UEs): {grown}"
    per_message = sum(many[f] - few[f] for f in PER_MESSAGE)
    assert per_message <= allowed * 900, f"{per_message} more calls to read and write 900 more UEs' messages"
