"""Malformed ns-3 settings (issue #55): each is refused by ``caviar-core validate`` and
``caviar-core run`` before anything runs, with exit status 2 and one line naming the key and
what was expected, never a traceback or an abort inside ns-3. ns-3 itself judges each value
(a parse in a child process, which alone aborts when ns-3 does). An abort that no check can
see ends the run naming the module, the phase and ns-3's words, in-process and over NATS.

The corpus runs in-process through ``caviar._core.main`` (ns-3 loads once); the values that
used to abort the process also go through the installed ``caviar-core`` script.
"""

from __future__ import annotations

import json
import subprocess

import pytest

from caviar import _core
from configs import caviar_core, caviar_env, nats_transport

BASE = """\
[episode]
ts = 0.5
steps = 2
seed = 1
stages = ["mobility", "communications", "link"]

[output]
name = "bad"
dir = "runs"

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
[modules.uav.params]
speed = 5.0
ue_id = "uav1"

[modules.comm]
stage = "communications"
plugin = "free-space-link"
[modules.comm.params]
tx_position = [0.0, 0.0, 60.0]
frequency_hz = 40e9
publish_link = true

[modules.net]
stage = "link"
plugin = "ns3-network"
[modules.net.params]
enb_position = [0.0, 0.0, 60.0]
"""

P = "modules.net.params."
CASES = [  # (id, lines under [modules.net.params], the key named, words the message must have)
    ("enum-name", 'attributes = { "ns3::LteEnbRrc::EpsBearerToRlcMapping" = "Bogus" }',
     'attributes."ns3::LteEnbRrc::EpsBearerToRlcMapping"', "RlcUmAlways"),
    ("time-word", 'attributes = { "ns3::LteRlcUm::ReorderingTimer" = "soon" }',
     'attributes."ns3::LteRlcUm::ReorderingTimer"', 'a time with its unit, such as "10ms"'),
    ("time-number-word", 'attributes = { "ns3::LteEnbRrc::ConnectionRequestTimeoutDuration" = "15 fortnights" }',
     'attributes."ns3::LteEnbRrc::ConnectionRequestTimeoutDuration"', "a time with its unit"),
    ("double-word", 'attributes = { "ns3::LteUePhy::TxPower" = "loud" }', 'attributes."ns3::LteUePhy::TxPower"',
     "expected a number, got 'loud'"),
    ("double-bool", 'attributes = { "ns3::LteUePhy::TxPower" = true }', 'attributes."ns3::LteUePhy::TxPower"',
     "expected a number, got 'true'"),
    ("bool-word", 'attributes = { "ns3::LteUePhy::EnableUplinkPowerControl" = "maybe" }',
     'attributes."ns3::LteUePhy::EnableUplinkPowerControl"', "true or false"),
    ("uint-negative", 'attributes = { "ns3::LteRlcUm::MaxTxBufferSize" = -5 }',
     'attributes."ns3::LteRlcUm::MaxTxBufferSize"', "an integer >= 0"),
    ("uint-too-large", 'attributes = { "ns3::LteRlcUm::MaxTxBufferSize" = 99999999999 }',
     'attributes."ns3::LteRlcUm::MaxTxBufferSize"', "within the attribute's range"),
    ("attribute-typo", 'attributes = { "ns3::LteUePhy::TxPowr" = 23 }', 'attributes."ns3::LteUePhy::TxPowr"',
     "no such attribute"),
    ("attribute-class", 'attributes = { "ns3::NoSuchPhy::TxPower" = 23 }', 'attributes."ns3::NoSuchPhy::TxPower"',
     "no such attribute"),
    ("attribute-bare", 'attributes = { "TxPower" = 23 }', 'attributes."TxPower"', "ns3::Class::Attribute"),
    ("p2p-rate-word", 'ran = "p2p"\np2p = { rate = "fast" }', "p2p.rate", 'a rate > 0 with its unit'),
    ("p2p-rate-spaced", 'ran = "p2p"\np2p = { rate = "10 gigs" }', "p2p.rate", "got '10 gigs'"),
    ("p2p-rate-zero", 'ran = "p2p"\np2p = { rate = "0bps" }', "p2p.rate", "a rate > 0"),
    ("p2p-rate-number", 'ran = "p2p"\np2p = { rate = 10 }', "p2p.rate", "str"),
    ("p2p-queue-word", 'ran = "p2p"\np2p = { queue = "lots" }', "p2p.queue", '"100p" or "64KB"'),
    ("p2p-queue-unit", 'ran = "p2p"\np2p = { queue = "100 parcels" }', "p2p.queue", "got '100 parcels'"),
    ("p2p-delay-negative", 'ran = "p2p"\np2p = { delay_s = -1.0 }', "p2p.delay_s", "a duration >= 0"),
    ("p2p-delay-infinite", 'ran = "p2p"\np2p = { delay_s = inf }', "p2p.delay_s", "inf"),
    ("p2p-unknown-key", 'ran = "p2p"\np2p = { speed = "10Mbps" }', "p2p.speed", "speed"),
    ("lte-scheduler", 'lte = { scheduler = "ns3::NoSuchScheduler" }', "lte.scheduler", "ns3::PfFfMacScheduler"),
    ("lte-scheduler-not-one", 'lte = { scheduler = "ns3::Node" }', "lte.scheduler", "LTE MAC schedulers"),
    ("lte-backhaul-rate", 'lte = { backhaul_rate = "10 gigs" }', "lte.backhaul_rate", "a rate > 0"),
    ("lte-backhaul-delay", "lte = { backhaul_delay_s = -0.001 }", "lte.backhaul_delay_s", "a duration >= 0"),
    ("lte-bandwidth", "lte = { bandwidth_rb = 7 }", "lte.bandwidth_rb", "6, 15, 25, 50, 75 or 100"),
    ("lte-rlc-buffer", "lte = { rlc_buffer_bytes = 100 }", "lte.rlc_buffer_bytes", "0 (sized from the load)"),
    ("lte-attach-loss", "lte = { attach_loss_db = nan }", "lte.attach_loss_db", "nan"),
    ("ran-nr", 'ran = "nr"', "ran", "5G-LENA"),
    ("transport", 'transport = "sctp"', "transport", "'udp' or 'tcp'"),
    ("payload", "payload_bytes = 10", "payload_bytes", "64..65000"),
    ("deadline", "deadline_s = -1.0", "deadline_s", ">= 0 s"),
    ("enb-position", "enb_position = [0.0, 0.0]", "enb_position", "[x, y, z]"),
    ("ues-empty", "ues = []", "ues", "distinct UE ids"),
    ("loss-from", 'loss_from = "beam"', "loss_from", "'pair' or 'path'"),
]
IDS = [c[0] for c in CASES]


def text_of(lines: str) -> str:
    base = BASE.replace("enb_position = [0.0, 0.0, 60.0]\n", "") if "enb_position" in lines else BASE
    return base + lines + "\n"


def test_the_corpus_is_large():
    assert len(CASES) >= 30


def _check(err: str, out: str, key: str, words: str) -> None:
    assert "Traceback" not in err + out and "NS_FATAL" not in err + out, err
    assert "materialize" not in err + out, err  # cling's noise held back
    first = err.splitlines()[0]
    assert first.startswith("error: ") and "cfg.toml:" in first, err
    assert f": {P}{key}: " in first, f"expected key {P}{key}: {first}"
    assert words in first, f"expected {words!r}: {first}"


@pytest.mark.parametrize("cid, lines, key, words", CASES, ids=IDS)
def test_a_malformed_ns3_setting_is_refused_by_validate_and_run(cid, lines, key, words, tmp_path, capfd,
                                                                 monkeypatch):
    path = tmp_path / "cfg.toml"
    path.write_text(text_of(lines))
    monkeypatch.chdir(tmp_path)
    for command in ("validate", "run"):
        code = _core.main(["caviar-core", command, "-q", str(path)] if command == "run"
                          else ["caviar-core", command, str(path)])
        out, err = capfd.readouterr()
        assert code == 2, f"{command}: exit {code}\n{out}{err}"
        _check(err, out, key, words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.toml"]  # no run directory


ABORTED_BEFORE = ["enum-name", "p2p-rate-word", "lte-scheduler"]
"""Values that took the process down inside ns-3 (exit 133 and a gdb backtrace) or passed
``validate`` and then did, before these checks (the others of the kind, "time-word",
"p2p-queue-word", "lte-backhaul-rate", take the same path; each process loads ns-3 for
about 10 s)."""


@pytest.mark.parametrize("cid", ABORTED_BEFORE)
def test_the_console_script_refuses_them_without_an_abort(cid, tmp_path):
    _, lines, key, words = CASES[IDS.index(cid)]
    (tmp_path / "cfg.toml").write_text(text_of(lines))
    for command in ("validate", "run"):
        p = subprocess.run([caviar_core(), command, "cfg.toml"], cwd=tmp_path, env=caviar_env(), capture_output=True,
                           text=True, timeout=300)
        assert p.returncode == 2, f"{command}: exit {p.returncode}\n{p.stdout}{p.stderr}"
        _check(p.stderr, p.stdout, key, words)
        assert len(p.stderr.splitlines()) == 1, p.stderr
    assert sorted(q.name for q in tmp_path.iterdir()) == ["cfg.toml"]


SRS = 'attributes = { "ns3::LteEnbRrc::SrsPeriodicity" = 7 }'
"""A value every check passes (an integer, as its checker wants) that ns-3 refuses only as it
builds the eNB, by aborting: "illecit SRS periodicity value 7"."""


@pytest.mark.parametrize("transport", ["in-process", "nats"])
def test_an_abort_inside_ns3_ends_the_run_naming_the_module_the_phase_and_ns3s_words(transport, tmp_path):
    text = text_of(SRS) + (nats_transport() if transport == "nats" else "")
    (tmp_path / "cfg.toml").write_text(text)
    p = subprocess.run([caviar_core(), "validate", "cfg.toml"], cwd=tmp_path, env=caviar_env(), capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr  # no check can see it
    p = subprocess.run([caviar_core(), "run", "cfg.toml", "-q", "--out", "run"], cwd=tmp_path, env=caviar_env(),
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 1, p.stderr
    line = next(ln for ln in p.stderr.splitlines() if ln.startswith("error:"))
    assert "module 'net' failed in setup" in line, p.stderr
    assert ("ns-3 aborted while building the network: illecit SRS periodicity value 7. Allowed values: 2 5 10 20 "
            "40 80 160 320 (lte-enb-rrc.cc:") in line, p.stderr
    assert "no heartbeat" not in p.stderr and "gdb" not in p.stderr and "#0 " not in p.stderr, p.stderr
    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["status"] == "failed", status
    error = status["error"]
    assert error["module"] == "net" and error["phase"] == "setup", error
    assert "illecit SRS periodicity value 7" in error["message"] and "\n" not in error["message"], error


def test_a_fatal_error_inside_a_guarded_call_is_an_exception_with_ns3s_words():
    """In this process: ns-3's NS_FATAL_ERROR ("Could not parse rate") becomes Ns3Aborted with
    its message and source line, what ns-3 wrote goes on the exception, and ns-3 goes on
    working for the next network."""
    from caviar_plugins.ns3 import simulator as sim

    g = sim.load()
    with pytest.raises(sim.Ns3Aborted) as e:
        with sim.guarded("parsing a rate"):
            g.caviar_ns3.RateBps("fast")  # DataRate("fast"): NS_FATAL_ERROR
    assert str(e.value).startswith("ns-3 aborted parsing a rate: Could not parse rate: fast (data-rate.cc:"), e.value
    assert "NS_FATAL, terminating" in e.value.__notes__[0]
    s = sim.Ns3Simulation(1, "p2p", p2p=sim.P2pSettings("10Mbps", 0.005, "100p"), warmup_s=0.0)
    try:
        assert s.send(0, 1, 5000, 1400) == 4
        s.run_until(1.0)
        assert [a.index for a in s.arrivals()] == [0, 1, 2, 3]
    finally:
        s.close()
    # The same through an overloaded constructor, which cppyy reports as one TypeError:
    with pytest.raises(sim.Ns3Aborted, match=r"ns-3 aborted parsing a rate: Could not parse rate: fast \(data-rate"):
        with sim.guarded("parsing a rate"):
            g.ns3.DataRate("fast")
