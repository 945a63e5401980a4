"""Load on the radio network (issue #41, part 3): FTP model 3 arrivals, a scheduler that
serves queued bytes only, file delays against a hand computation, and the twin's own
messages carried and delivered."""

from __future__ import annotations

import math

import numpy as np
import pytest

import caviar
from caviar_plugins.network.traffic import Backlog, Carried, FtpSettings, Queues, TrafficSettings, Transfer
from caviar_plugins.radio.link_level import LinkLevel
from caviar_plugins.radio.link_settings import LinkSettings
from configs import episode, module, output, waypoint_uav
from network_configs import (
    BAND,
    MAPS,
    REPORTS,
    STAGES,
    line_movers,
    mover,
    radio_network,
    reported,
    run_network,
    site,
    ue_reports,
)

SLOT_S = 0.5e-3  # 30 kHz


def test_ftp3_files_arrive_as_a_poisson_process_of_the_given_rate():
    rate, step_s, steps = 4.0, 0.1, 3000
    q = Queues(TrafficSettings(downlink="ftp3", ftp=FtpSettings(file_bytes=1000, arrival_rate_hz=rate)), seed=3)
    counts, times = [], []
    for k in range(steps):
        before = len(q.queues.get(("u", "downlink"), []))
        q.backlog(k * step_s, ["u"], ["car"], "downlink", 200, SLOT_S)
        queue = q.queues.get(("u", "downlink"), [])
        counts.append(len(queue) - before)
        times += [x.queued_s for x in queue[before:]]
        assert all(k * step_s <= x.queued_s < (k + 1) * step_s for x in queue[before:])
    counts = np.array(counts)
    mean = rate * step_s
    # Poisson: mean λT (within 4 standard errors) and variance equal to the mean.
    assert abs(counts.mean() - mean) < 4 * math.sqrt(mean / steps)
    assert 0.85 < counts.var() / counts.mean() < 1.15
    gaps = np.diff(times)  # exponential inter-arrival times of mean 1/λ
    assert gaps.mean() == pytest.approx(1 / rate, rel=0.05)
    assert np.mean(gaps > 1 / rate) == pytest.approx(math.exp(-1), abs=0.02)


def _one_ue_shannon(sinr_db: float, n_prb: int = 51):
    """A Shannon link level for one UE at a fixed SINR, and its bits per slot by hand."""
    link = LinkLevel(LinkSettings(num_prb=n_prb, link_model="shannon"), n_cell=1)
    per_slot = n_prb * 12 * 30e3 * math.log2(1 + 10 ** (sinr_db / 10)) * SLOT_S
    return link, per_slot


def test_file_delay_and_user_perceived_throughput_match_a_hand_computation():
    """Two 0.5 MB files queued at t = 0, one UE at 10 dB: each completes at the end of the
    slot in which the bits before it and its own are through."""
    link, per_slot = _one_ue_shannon(10.0)
    q = Queues(TrafficSettings(downlink="none"), seed=0)
    bits = 8 * 500_000
    q.queues[("u", "downlink")] = [Transfer("u", "downlink", "ftp", 0.0, 500_000, bits) for _ in range(2)]
    slots = 200
    done = []
    for k in range(3):
        t = k * slots * SLOT_S
        b = q.backlog(t, ["u"], ["car"], "downlink", slots, SLOT_S)
        res = link.run(np.full((slots, 1), 10.0), np.array([0]), backlog=b)
        assert np.all(res.delivered_bits <= per_slot + 1e-6)
        done += q.serve(t, ["u"], "downlink", res.delivered_bits, SLOT_S)
    assert len(done) == 2
    for n, (x, at) in enumerate(done, start=1):
        hand = math.ceil(n * bits / per_slot) * SLOT_S
        assert at == pytest.approx(hand, abs=1e-9)
        assert 8 * x.size_bytes / (at - x.queued_s) / 1e6 == pytest.approx(bits / hand / 1e6, rel=1e-9)
    assert q.queued_bytes("u", "downlink") == 0


def test_the_scheduler_grants_nothing_to_an_empty_buffer():
    """Sionna SYS, one cell, two UEs at the same SINR: the one with nothing queued gets no
    PRB; the other gets every slot until its bytes are through, then nobody is scheduled;
    a UE whose bits arrive at slot 40 is first scheduled in the group of slots starting there."""
    link = LinkLevel(LinkSettings(num_prb=51, harq_processes=8), n_cell=1, seed=1)
    slots = 80
    sinr = np.full((slots, 3), 15.0)
    arrivals = np.zeros((slots, 3))
    arrivals[40, 2] = 1e5
    backlog = Backlog(np.array([0.0, 2e5, 0.0]), arrivals)
    res = link.run(sinr, np.array([0, 0, 0]), backlog=backlog)
    assert res.prbs[0] == 0 and res.scheduled_slots[0] == 0 and res.delivered_bits[:, 0].sum() == 0
    assert res.delivered_bits[:, 1].sum() == pytest.approx(2e5)  # all of it, no padding counted
    assert res.delivered_bits[:40, 2].sum() == 0 and res.delivered_bits[40:, 2].sum() == pytest.approx(1e5)
    last = np.flatnonzero(res.delivered_bits[:, 1])[-1]
    assert not res.cells_active[(last // 8 + 1) * 8:40].any()  # empty buffers: the cell is silent
    assert res.decoded_bits[1] == pytest.approx(2e5)


def _one_site(height: float, carried: dict, *, uplink: dict | None = None, traffic: dict | None = None,
              **params) -> str:
    """Site A (one sector, no downtilt) at ``height`` m, a 1×1 array, Shannon's link level,
    the UEs' antennas at 0 m, uplink power control (P0 −90 dBm, α 1; ``uplink`` over it), no
    load of its own (``traffic`` over that) and ``carried`` carried; ``params``: the others."""
    return radio_network([site("A", [0.0, 0.0, height], [0.0], 0.0)], **BAND, **params, array=[1, 1],
                         link_model="shannon", antenna_height_m=0.0,
                         uplink={"p0_dbm": -90.0, "alpha": 1.0, **(uplink or {})},
                         traffic={"downlink": "none", "uplink": "none", **(traffic or {}), "carry": [carried]})


def _carry(x: float = 200.0, size: int = 60_000, topic: str = "payload.*", sent=(0, 1, 2), modules: str = "",
           **traffic) -> str:
    """8 steps of 10 ms: u1 standing ``x`` m from site A (at its height) sends ``size`` bytes
    at the steps ``sent`` (sample_plugins:Payloads), the network carries ``topic`` uplink and
    delivers it on delivered.*; ``modules``: more modules before the network's."""
    return (episode(0.01, [*STAGES, "after"], steps=8, seed=2)
            + output(analysis=[*REPORTS, *MAPS, "network.transfers", "delivered.*"])
            + line_movers(mover("u1", [x, 0.0, 1.5]))
            + module("sender", "mobility", "sample_plugins:Payloads", {"ue": "u1", "size": size, "steps": list(sent)})
            + modules
            + _one_site(1.5, {"topic": topic, "deliver_to": "delivered"}, subcarrier_spacing_hz=30e3,
                        tx_power_dbm=46.0, uplink={"ue_max_power_dbm": 23.0}, traffic=traffic))


def test_a_carried_message_is_delivered_once_the_uplink_has_carried_its_bytes(tmp_path):
    """A UE 200 m from its cell sends 60 kB at steps 0, 1 and 2 (10 ms each): each message
    arrives on delivered.u1 at the step its last byte got through, its delay and UPT on
    network.transfers agree with the uplink's own throughput, and nothing more is sent."""
    log = run_network(tmp_path, _carry())
    transfers = [m.data for m in log.decoded("network.transfers")]
    assert [x["queued_s"] for x in transfers] == pytest.approx([0.0, 0.01, 0.02])
    assert all(x["source"].startswith("payload.") and x["direction"] == "uplink" for x in transfers)
    delivered = [(m.time, m.data) for m in log.decoded("delivered.u1")]
    assert [d[0] for d in delivered] == pytest.approx([math.floor(x["delivered_s"] / 0.01) * 0.01 for x in transfers])
    assert [bytes(d[1])[:1] for d in delivered] == [b"\x00", b"\x01", b"\x02"]  # the payloads, unchanged
    ue = ue_reports(log)
    sent_mbit = sum(u["ul_throughput_mbps"] * 0.01 for u in ue)
    assert sent_mbit == pytest.approx(3 * 60_000 * 8 / 1e6, rel=1e-6)  # only the queued bytes
    assert ue[-1]["ul_queue_bytes"] == 0
    # Shannon at the UE's uplink SINR over the 51 PRBs: a message queued at its step's start
    # (the one before it was through) takes ⌈B / bits per slot⌉ slots.
    per_slot = 51 * 12 * 30e3 * math.log2(1 + 10 ** (ue[0]["ul_sinr_db"] / 10)) * 0.5e-3
    hand = math.ceil(60_000 * 8 / per_slot) * 0.5e-3
    assert hand < 0.01  # (each within its step)
    for x in transfers:
        assert x["delay_s"] == pytest.approx(hand, abs=1e-9)
        assert x["upt_mbps"] == pytest.approx(8 * 60_000 / hand / 1e6, rel=1e-5)
    # caviar-core report: the delay and user-perceived throughput CDFs, and their numbers.
    import json

    rep = reported(tmp_path)
    assert (rep / "network-transfers.png").stat().st_size > 15_000
    group = json.loads((rep / "network.json").read_text())["transfers"]["payload.* uplink"]
    assert group["delivered"] == 3 and group["lost"] == 0 and group["bytes_mean"] == 60_000
    assert group["delay_s"]["p50"] == pytest.approx(hand, abs=1e-6)


def test_traffic_naming_a_topic_no_module_publishes_is_refused_before_the_run(tmp_path):
    cfg = tmp_path / "net.toml"
    cfg.write_text(_carry(size=100, topic="camera.*"))
    with pytest.raises(caviar.ConfigError) as e:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    text = str(e.value)
    assert "net.toml:" in text and "modules.net.params.traffic.carry.0.topic" in text
    assert "'camera.*'" in text and "no other module publishes it" in text, text
    assert not (tmp_path / "run").exists()
    cfg.write_text(_carry(size=100, uplink="ftp4"))
    with pytest.raises(caviar.ConfigError) as e:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    assert "traffic.uplink" in str(e.value) and "full-buffer" in str(e.value), e.value
    cfg.write_text(_carry(size=100, by_type={"car": {"downlink": "ftp4"}}))
    with pytest.raises(caviar.ConfigError) as e:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    assert "traffic.by_type.car.downlink" in str(e.value) and "ftp3" in str(e.value), e.value


def test_each_ue_type_may_have_a_load_of_its_own():
    """``by_type``: the cars download FTP files while the UAV downloads nothing; in the uplink
    the cars keep the default full buffer and the UAV sends nothing of its own."""
    q = Queues(TrafficSettings(downlink="ftp3", ftp=FtpSettings(file_bytes=1000, arrival_rate_hz=50.0),
                               by_type={"UAV": {"downlink": "none", "uplink": "none"}}), seed=1)
    ids, types = ["car1", "uav1", "car2"], ["car", "UAV", "car"]
    dl = [q.backlog(k * 0.1, ids, types, "downlink", 200, SLOT_S) for k in range(10)]
    files = sum(b.arrivals_bits for b in dl).sum(axis=0) / 8000
    assert files[1] == 0 and files[0] > 20 and files[2] > 20  # λT = 50 per UE
    ul = q.backlog(0.0, ids, types, "uplink", 200, SLOT_S)
    assert list(ul.queued_bits) == [math.inf, 0.0, math.inf] and not ul.arrivals_bits.any()
    assert q.report("uav1", "UAV", ("downlink", "uplink")) == {"dl_queue_bytes": 0, "ul_queue_bytes": 0}
    assert q.report("car1", "car", ("downlink", "uplink")).keys() == {"dl_queue_bytes"}


def test_a_loaded_network_resumes_to_the_same_messages(tmp_path, cli):
    """The queues (files part-delivered across a checkpoint), the FTP arrival stream and the
    link levels' loops are the state: a SIGKILLed run with FTP load both ways resumes to the
    reference's messages, bit for bit."""
    import random

    from conftest import write_config
    from network_configs import cars_in_the_canyon
    from test_resume_plugins import _resumes_to_the_reference

    text = cars_in_the_canyon(uplink={"p0_dbm": -80.0}, traffic={
        "downlink": "ftp3", "uplink": "ftp3", "ftp": {"file_bytes": 300000, "arrival_rate_hz": 30.0}})
    cfg = write_config(tmp_path, text)
    kill = random.Random(41).randrange(9, 20)
    log = _resumes_to_the_reference(tmp_path, cli, cfg, [], kill, every=7, steps=24)
    transfers = [m.data for m in log.decoded("network.transfers")]
    assert {x["direction"] for x in transfers} == {"downlink", "uplink"}
    assert any(x["delay_s"] > 0.02 for x in transfers)  # some crossed a step (and a checkpoint)


def test_in_process_and_over_nats_a_carried_message_records_the_same(tmp_path, cli):
    (tmp_path / "net.toml").write_text(_carry())
    cli("run", "net.toml", "-q", "--out", "inproc", check=0)
    cli("run", "net.toml", "-q", "--out", "nats", "--set", 'transport.kind="nats"', check=0)
    a, b = (caviar.load_run(tmp_path / d).messages.drop("seq") for d in ("inproc", "nats"))
    assert a.height == b.height > 40 and a.equals(b)
    assert (a["topic"] == "delivered.u1").sum() == 3


def _mission(network: bool = True) -> str:
    """30 steps of 0.1 s: the UAV flies route.csv, sees a person at step 3, and the mission
    uploads 2 images of 1 MB over the network (without one: no radio network), carried by
    site A at 30 m."""
    return (episode(0.1, ["mobility", "ai", "communications", "mission"], steps=30, seed=5)
            + output(analysis=["network.ue", "network.events", "network.cells", *MAPS, "network.transfers",
                               "mission.rescue", "mission.result"])
            + waypoint_uav(speed=10.0, end_at_last=False)
            + module("eyes", "ai", "sample_plugins:OneDetection", {"at": 3})
            + (_one_site(30.0, {"topic": "mission.upload", "size_field": "bytes"}) if network else "")
            + module("mission", "mission", "mission", {"upload": "network", "images": 2, "image_mb": 1.0}))


def test_with_the_network_option_the_uav_hovers_until_its_upload_is_delivered(tmp_path, cli):
    """A person seen at step 3 (t = 0.3 s): the mission queues 2 MB at the UAV, which holds
    still from the next step until network.transfers says the bytes are through, then flies on. The upload is
    served from the next step (the mission runs after the network) and takes ⌈B / bits per
    slot⌉ slots of Shannon at the UAV's uplink SINR, by hand; the hover is that long."""
    (tmp_path / "route.csv").write_text("X,Y,Z\n300,0,30\n600,0,30\n")
    (tmp_path / "net.toml").write_text(_mission())
    cli("run", "net.toml", "-q", "--out", "run", check=0)
    log = caviar.load_run(tmp_path / "run")
    x = {round(m.time, 6): m.data["position"]["x"] for m in log.decoded("3D.mobility.positions")}
    (upload,) = [m.data for m in log.decoded("network.transfers")]
    assert upload["source"] == "mission.upload" and upload["bytes"] == 2_000_000 and upload["queued_s"] == 0.3
    ue = {round(m.time, 6): m.data for m in log.decoded("network.ue")}
    per_slot = 51 * 12 * 30e3 * math.log2(1 + 10 ** (ue[0.4]["ul_sinr_db"] / 10)) * 0.5e-3
    hand = 0.4 + math.ceil(16e6 / per_slot) * 0.5e-3
    assert upload["delivered_s"] == pytest.approx(hand, abs=1e-9)
    done = math.floor(hand / 0.1 + 1e-9) / 10  # the step whose slots finished it
    assert 0.4 < done < 2.5
    # (the flight hears the mission a step later, and a position is where the last step left it)
    held = [t for t in sorted(x) if 0.4 - 1e-9 <= t <= done + 0.1 + 1e-9]
    assert len(held) >= 3 and len({x[t] for t in held}) == 1  # still until the step after delivery
    assert x[round(done + 0.2, 6)] > x[round(done + 0.1, 6)]  # then on its way
    (rescue,) = [m.data for m in log.decoded("mission.rescue")]
    assert rescue["uploaded"] and rescue["hover_s"] == pytest.approx(hand - 0.3, abs=1e-6)
    assert rescue["throughput"] == pytest.approx(16 / (hand - 0.3), rel=1e-5)
    # upload = "network" with no radio network to deliver: refused, naming the key.
    (tmp_path / "bad.toml").write_text(_mission(network=False))
    p = cli("validate", "bad.toml", check=2)  # (a configuration error)
    assert "bad.toml:" in p.stderr and "modules.mission.params.upload" in p.stderr, p.stderr
    assert "'network.transfers' — no other module publishes it" in p.stderr, p.stderr


def test_a_ue_that_leaves_reports_what_it_had_not_sent_as_lost(tmp_path):
    """Nothing is lost silently: 2 MB queued at step 0 at a UE that leaves at step 2 come out
    on network.transfers as lost, with the bytes still waiting; what it delivered before counts."""
    leaves = module("leave", "mobility", "sample_plugins:Leaves", {"ue": "u1", "at": 2})
    log = run_network(tmp_path, _carry(size=2_000_000, sent=[0], modules=leaves))
    (lost,) = [m.data for m in log.decoded("network.transfers")]
    sent = sum(u["ul_throughput_mbps"] * 0.01 * 1e6 / 8 for u in ue_reports(log))
    assert lost["lost"] and lost["bytes"] == 2_000_000 and "delivered_s" not in lost
    assert 0 < sent < 2_000_000 and lost["bytes_left"] == pytest.approx(2_000_000 - sent, abs=1)
    assert not log.decoded("delivered.u1")


def test_a_higher_priority_message_overtakes_a_bulk_transfer_queued_before_it():
    """Strict priority per UE: a 60 kB frame (priority 1) queued after a 4 MB upload (0) at
    10 dB (Shannon) goes first, in ⌈frame bits / bits per slot⌉ slots (the cell's other UE has
    nothing to send); the upload finishes when both are through; two frames keep their order."""
    link, per_slot = _one_ue_shannon(10.0)
    upload = Carried(topic="mission.upload", size_field="bytes")
    frame = Carried(topic="3D.camera.*", priority=1)
    q = Queues(TrafficSettings(uplink="none", carry=[upload, frame]), seed=0)
    q.queue_message(0.0, "u", "mission.upload", {"bytes": 4_000_000}, upload)
    q.queue_message(0.0, "u", "3D.camera.u", np.zeros(60_000, np.uint8), frame)
    q.queue_message(0.0, "u", "3D.camera.u", np.ones(60_000, np.uint8), frame)
    done = []
    for k in range(7):
        t = k * 0.1
        b = q.backlog(t, ["v", "u"], ["car", "UAV"], "uplink", 200, SLOT_S)  # (v, in the same cell: nothing to send)
        res = link.run(np.full((200, 2), 10.0), np.array([0, 0]), backlog=b)
        assert res.delivered_bits[:, 0].sum() == 0
        done += q.serve(t, ["v", "u"], "uplink", res.delivered_bits, SLOT_S)
    assert [x.source for x, _ in done] == ["3D.camera.u", "3D.camera.u", "mission.upload"]
    assert done[0][0].payload[0] == 0 and done[1][0].payload[0] == 1
    for n, bits in ((0, 480_000), (1, 960_000), (2, 960_000 + 32e6)):
        assert done[n][1] == pytest.approx(math.ceil(bits / per_slot) * SLOT_S, abs=1e-9)
