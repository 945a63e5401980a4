"""The ns3-network plugin: the UAVs' images over the real ns-3 (PyPI's ns3 wheel), in
lockstep with the engine, each check against a computation by hand."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import caviar
from caviar_plugins.ns3 import simulator as sim
from configs import episode, module, nats_transport, output, waypoint_uav, write_route
from conftest import ROOT

SPEED_OF_LIGHT = 299_792_458.0
KT_DBM_HZ = 10 * math.log10(1.380649e-23 * 290 * 1e3)  # ns-3 LTE's thermal noise, dBm/Hz
WIRE = sim.HEADER_BYTES + sim.UDP_IP_BYTES + sim.PPP_BYTES  # bytes a p2p link adds per packet


def test_point_to_point_packets_arrive_after_serialisation_and_propagation_and_a_full_queue_drops():
    s = sim.Ns3Simulation(1, "p2p", p2p=sim.P2pSettings("10Mbps", 0.005, "100000p"), warmup_s=0.0)
    try:
        assert s.send(0, 7, 20_000, 1400) == 15  # 14 × 1400 + 400
        s.run_until(1.0)
        got = s.arrivals()
        sizes = [1400] * 14 + [400]
        done, expected = 0.0, []
        for size in sizes:  # back to back on the wire: each waits for the ones before it
            done += (size + WIRE) * 8 / 10e6
            expected.append(done + 0.005)
        assert [a.index for a in got] == list(range(15)) and all(a.image == 7 for a in got)
        assert [a.bytes for a in got] == [n + sim.HEADER_BYTES for n in sizes]
        assert np.allclose([a.time_s for a in got], expected, atol=1e-9)
    finally:
        s.close()
    s = sim.Ns3Simulation(1, "p2p", p2p=sim.P2pSettings("10Mbps", 0.005, "5p"), warmup_s=0.0)
    try:
        s.send(0, 1, 20_000, 1400)
        s.run_until(1.0)
        # One packet goes straight onto the wire, five wait in the DropTail queue, the rest drop.
        assert [a.index for a in s.arrivals()] == [0, 1, 2, 3, 4, 5]
    finally:
        s.close()


def _cqi_edges(amc) -> list[float]:
    """SINR (dB) at which each CQI starts, by ns-3's own AMC (Piro's rule: spectral
    efficiency log2(1 + SINR/Γ), Γ = -ln(5·BER)/1.5, BER 5e-5)."""
    gamma = -math.log(5 * 5e-5) / 1.5
    edges = []
    for sinr_db in np.arange(-10, 30, 0.01):
        cqi = int(amc.GetCqiFromSpectralEfficiency(math.log2(1 + 10 ** (sinr_db / 10) / gamma)))
        while len(edges) <= cqi:
            edges.append(float(sinr_db))
    return edges


NRB = 25  # uplink RBs


def _lte_at_mid_cqi8(ues: int):
    """An LTE network whose UEs (23 dBm, no power control, 200 m from the eNB) each reach it
    at the SINR in the middle of ns-3's CQI 8, far from either decision edge: the network,
    ns-3's AMC and that SINR (dB)."""
    tx_dbm, nf_db = 23.0, 5.0  # UE power, the eNB's noise figure (ns-3's default)
    s = sim.Ns3Simulation(ues, "lte", lte=sim.LteSettings(bandwidth_rb=NRB, rlc_buffer_bytes=64 << 20),
                          attributes={"ns3::LteUePhy::EnableUplinkPowerControl": False,
                                      "ns3::LteUePhy::TxPower": tx_dbm})
    amc = s.ns.CreateObject[s.ns.LteAmc]()
    edges = _cqi_edges(amc)
    target = (edges[8] + edges[9]) / 2
    # The UE's power spread over the uplink band, against kT·B·NF at the eNB.
    loss = tx_dbm - target - (KT_DBM_HZ + nf_db + 10 * math.log10(NRB * 180e3))
    s.set_enb_position([0, 0, 25])
    for ue in range(ues):
        s.set_position(ue, [200, 50 * ue, 1.5])
        s.set_loss(ue, loss)
    return s, amc, target


def test_lte_uplink_at_a_fixed_loss_runs_at_the_rate_of_the_mcs_ns3_amc_picks():
    s, amc, target = _lte_at_mid_cqi8(1)
    nrb = NRB
    try:
        s.uplink(), s.arrivals()
        t0 = s.now()
        s.send(0, 1, 4_000_000, 1400)  # more than a second's worth: the buffer never empties
        s.run_until(t0 + 1.2)
        got = s.arrivals()
        up = s.uplink()[0]
        assert up.sinr_db == pytest.approx(target, abs=0.1)  # the eNB measures what Friis-free arithmetic says
        cqi = int(amc.GetCqiFromSpectralEfficiency(math.log2(1 + 10 ** (target / 10) / (-math.log(2.5e-4) / 1.5))))
        mcs = int(amc.GetMcsFromCqi(cqi))
        assert cqi == 8 and up.mcs_mode == mcs
        rate = amc.GetUlTbSizeFromMcs(mcs, nrb) * 1000  # bit/s: one transport block per 1 ms TTI
        late = [a for a in got if a.time_s > t0 + 0.2]  # after the first grants
        measured = sum(a.bytes for a in late) * 8 / (late[-1].time_s - late[0].time_s)
        print(f"grants {up.grants} in 1200 TTIs, TB {up.tb_bytes * 8 / 1.2 / 1e6:.3f} Mbit/s; "
              f"SINR {up.sinr_db:.2f} dB, CQI {cqi}, MCS {mcs}: TBS rate {rate / 1e6:.3f} Mbit/s, "
              f"UDP payload {measured / 1e6:.3f} Mbit/s")
        assert measured == pytest.approx(rate, rel=0.10)
        assert measured < rate  # headers (UDP/IP, PDCP, RLC, MAC) take their share
    finally:
        s.close()


def test_two_ues_share_the_uplink_each_at_its_half_of_the_rbs():
    """ns-3's proportional-fair uplink scheduler gives each of two backlogged UEs half the
    band (12 of 25 RBs); the MCS still comes from the SRS SINR over the whole band."""
    s, amc, target = _lte_at_mid_cqi8(2)
    nrb = NRB
    try:
        s.uplink(), s.arrivals()
        t0 = s.now()
        for ue in (0, 1):
            s.send(ue, ue, 3_000_000, 1400)
        s.run_until(t0 + 1.2)
        got = s.arrivals()
        mcs = int(amc.GetMcsFromCqi(8))
        rate = amc.GetUlTbSizeFromMcs(mcs, nrb // 2) * 1000  # bit/s on 12 RBs
        for ue, up in enumerate(s.uplink()):
            assert up.sinr_db == pytest.approx(target, abs=0.1) and up.mcs_mode == mcs
            late = [a for a in got if a.ue == ue and a.time_s > t0 + 0.2]
            measured = sum(a.bytes for a in late) * 8 / (late[-1].time_s - late[0].time_s)
            print(f"UE {ue}: {measured / 1e6:.3f} Mbit/s against {rate / 1e6:.3f} on 12 RBs at MCS {mcs}")
            assert measured == pytest.approx(rate, rel=0.10) and measured < rate
    finally:
        s.close()


def flight(ts: float, speed: float, net: str, camera: dict | None = None) -> str:
    """A UAV flying route.csv at ``speed`` with its camera (``camera``: its params), a
    free-space link from a mast at 60 m and its images over ns3-network, whose params are
    the lines ``net``."""
    return (episode(ts, ["mobility", "camera", "communications", "link"], seed=1)
            + output(name="ns3", analysis=["communications.throughput", "communications.state", "network.ns3.link",
                                           "ai.image_quality", "ai.images.*"], exclude=["3D.camera.>", "ai.images.*"])
            + waypoint_uav(speed=speed) + module("camera", "camera", "camera", camera)
            + module("comm", "communications", "free-space-link",
                     "tx_position = [0.0, 0.0, 60.0], frequency_hz = 40e9, publish_link = true")
            + module("net", "link", "ns3-network", net, params_table=True))


def _fly(tmp_path, net: str, route: list[list[float]], ts=0.5, speed=20.0, transport=None, camera=None):
    write_route(tmp_path, route)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(flight(ts, speed, net, camera) + (transport or ""))
    with caviar.Simulation.from_toml(cfg, out=tmp_path / "run") as s:
        return s.run(progress=False)


def test_point_to_point_image_delay_is_propagation_plus_serialisation_plus_queueing(tmp_path):
    """Each 57.6 kB image takes longer than a step to serialise at 0.8 Mbit/s: the next
    one waits behind it, and the wait grows image after image."""
    rate, delay, payload = 0.8e6, 0.004, 1400
    log = _fly(tmp_path, f'ran = "p2p"\np2p = {{ rate = "800kbps", delay_s = {delay} }}\ndeadline_s = 10.0\n'
                         f"payload_bytes = {payload}", [[0, 0, 40], [60, 0, 40]], speed=10.0)
    images = [m.data for m in log.decoded("ai.image_quality")]
    assert len(images) >= 10 and all(d["complete"] and d["packets_lost"] == 0 for d in images)
    free = 0.0  # when the link finishes the previous image
    for d in images:
        n = d["bytes_sent"]
        sizes = [payload] * (n // payload) + ([n % payload] if n % payload else [])
        start = max(d["sent_at"], free)
        free = start + sum(size + WIRE for size in sizes) * 8 / rate
        assert d["delay_s"] == pytest.approx(free + delay - d["sent_at"], abs=1e-9), d
    queued = [d["delay_s"] for d in images]
    assert queued[-1] > queued[0] + 0.5  # queueing builds up
    assert images[0]["psnr_db"] == 99.0  # a complete image is the image


def test_a_uav_flying_out_of_coverage_loses_more_and_its_images_degrade(tmp_path):
    tx_dbm, nrb, nf_db = 10.0, 25, 5.0
    net = ('loss_from = "path"\nenb_position = [0.0, 0.0, 60.0]\n'
           'attributes = { "ns3::LteUePhy::EnableUplinkPowerControl" = false, "ns3::LteUePhy::TxPower" = 10 }')
    log = _fly(tmp_path, net, [[30, 0, 60], [750, 0, 60]], ts=1.0, speed=24.0)
    images = [m.data for m in log.decoded("ai.image_quality")]
    links = [m.data for m in log.decoded("network.ns3.link")]
    positions = {m.step: m.data["position"] for m in log.decoded("3D.mobility.positions")}
    distance = np.array([math.dist((positions[m.step]["x"], positions[m.step]["y"], positions[m.step]["z"]),
                                   (0, 0, 60)) for m in log.decoded("network.ns3.link")])
    # The loss ns-3 was given is Friis at 40 GHz, and the SINR the eNB measured follows from it.
    friis_db = 20 * np.log10(4 * np.pi * distance * 40e9 / SPEED_OF_LIGHT)
    assert np.allclose([d["loss_db"] for d in links], friis_db, atol=0.01)
    measured = np.array([np.nan if d["sinr_db"] is None else d["sinr_db"] for d in links])
    hand = tx_dbm - friis_db - (KT_DBM_HZ + nf_db + 10 * math.log10(nrb * 180e3))
    assert np.nanmax(np.abs(measured[1:] - hand[1:])) < 0.2
    loss = np.array([d["loss_rate"] for d in images])
    quality = np.array([d["psnr_db"] for d in images])
    print("loss", np.round(loss, 2), "\nPSNR", np.round(quality, 1))
    assert loss[:5].max() == 0.0 and quality[:5].min() == 99.0  # near the cell: every byte arrives
    assert loss[-5:].min() > 0.5 and quality[-5:].max() < 20.0  # far out: most of each image is lost
    rank = np.corrcoef(np.argsort(np.argsort(distance[:len(loss)])), np.argsort(np.argsort(loss)))[0, 1]
    assert rank > 0.8  # loss rises with distance (Spearman)
    # caviar-core report's figure and numbers of the same run
    from caviar_plugins.ns3.report import figures

    png, numbers = figures(log, tmp_path / "report")
    assert png.stat().st_size > 20_000
    summary = json.loads(numbers.read_text())["ues"]["uav1"]
    assert summary["images"] == len(images) and summary["complete"] == sum(d["complete"] for d in images)
    assert summary["loss_rate"] == pytest.approx(1 - sum(d["bytes_received"] for d in images)
                                                 / sum(d["bytes_sent"] for d in images), abs=1e-4)


def test_over_tcp_every_image_arrives_whole_and_the_stream_is_cut_at_image_boundaries(tmp_path):
    log = _fly(tmp_path, 'transport = "tcp"\nenb_position = [0.0, 0.0, 60.0]', [[30, 0, 60], [90, 0, 60]],
               speed=10.0)
    images = [m.data for m in log.decoded("ai.image_quality")]
    assert len(images) >= 10
    assert all(d["complete"] and d["bytes_received"] == d["bytes_sent"] == 160 * 120 * 3 for d in images)
    assert all(d["psnr_db"] == 99.0 and 0 < d["delay_s"] < 0.5 for d in images)
    links = [m.data for m in log.decoded("network.ns3.link")]
    # The ground station received the images' bytes and nothing else (TCP's own headers aside).
    assert sum(d["delivered_bytes"] for d in links) == sum(d["bytes_sent"] for d in images)


LARGE = 333 * 200 * 3  # 199,800 bytes: more than ns-3's RLC buffer held before it was sized from the load


@pytest.mark.parametrize("loss_db", [100.0, 110.0])
def test_an_image_larger_than_128_kib_arrives_whole_at_a_good_loss(loss_db):
    """Before the UE's RLC buffer was sized from the load, its 128 KiB kept 36 % of a
    199,800-byte image out at every loss, and a saturated link carried 2.04 Mbit/s."""
    s = sim.Ns3Simulation(1, "lte", attributes={"ns3::LteUePhy::TxPower": 23})
    try:
        s.set_enb_position([0, 0, 25])
        s.set_position(0, [100, 0, 1.5])
        s.set_loss(0, loss_db)
        s.arrivals(), s.uplink()
        t0 = s.now()
        packets = s.send(0, 1, LARGE, 1400)
        s.run_until(t0 + 0.5)
        got = s.arrivals()
        assert packets == math.ceil(LARGE / 1400) == 143
        assert sorted(a.index for a in got) == list(range(143))  # every packet, none twice
        assert sum(a.bytes for a in got) == LARGE + 143 * sim.HEADER_BYTES
        assert s.rlc_buffer[0] >= 2 * (LARGE + 143 * (sim.HEADER_BYTES + sim.UDP_IP_BYTES + sim.PDCP_BYTES))
    finally:
        s.close()


def test_the_plugin_delivers_large_images_whole_and_counts_the_applications_bytes(tmp_path):
    """A 333×200 camera's images (199,800 bytes) over LTE within 60 m of the cell: each one
    arrives whole, and network.ns3.link counts the images' bytes, not the plugin's 8-byte
    header on each packet."""
    log = _fly(tmp_path, 'loss_from = "path"\nenb_position = [0.0, 0.0, 60.0]', [[30, 0, 60], [50, 0, 60]],
               speed=10.0, camera={"width": 333, "height": 200, "supersample": 1})
    images = [m.data for m in log.decoded("ai.image_quality")]
    links = [m.data for m in log.decoded("network.ns3.link")]
    assert len(images) >= 4
    assert all(d["complete"] and d["bytes_sent"] == d["bytes_received"] == LARGE for d in images), images
    assert all(d["psnr_db"] == 99.0 and d["packets_lost"] == 0 for d in images)
    # Every image sent arrived within its step: the steps' delivered bytes add up to the images'.
    assert sum(d["delivered_bytes"] for d in links) == LARGE * len(images)
    for d in links:
        assert d["throughput_mbps"] == pytest.approx(d["delivered_bytes"] * 8 / 0.5 / 1e6, rel=1e-12)


def test_a_fixed_rlc_buffer_that_cannot_hold_an_image_is_warned_about_and_cuts_each_image(tmp_path):
    """``lte.rlc_buffer_bytes = 32768`` against 57,600-byte images: a warning naming the
    module and the setting, and each image cut where the buffer is full. The RLC counts a
    packet as its PDCP PDU: 1400 bytes of image, the 8-byte header, UDP/IP and PDCP's 2 bytes."""
    with pytest.warns(UserWarning, match=r"modules\.net\.params\.lte\.rlc_buffer_bytes = 32768 cannot hold one "
                                         r"image of UE 'uav1' \(57600 bytes"):
        log = _fly(tmp_path, 'loss_from = "path"\nenb_position = [0.0, 0.0, 60.0]\nlte = { rlc_buffer_bytes = 32768 }',
                   [[30, 0, 60], [50, 0, 60]], speed=10.0)
    images = [m.data for m in log.decoded("ai.image_quality")]
    room, fits = 32768, 0  # the packets, in order, that find room (all at once: nothing drains meanwhile)
    for n in [1400] * (57600 // 1400) + [57600 % 1400]:
        if n + sim.HEADER_BYTES + sim.UDP_IP_BYTES + sim.PDCP_BYTES <= room:
            room -= n + sim.HEADER_BYTES + sim.UDP_IP_BYTES + sim.PDCP_BYTES
            fits += n
    assert fits == 22 * 1400 + 200  # the last, short packet still fits
    assert len(images) >= 4
    assert all(d["bytes_received"] == fits and not d["complete"] for d in images), images


BIN = os.path.dirname(sys.executable)


def test_killing_the_ns3_worker_stops_the_run_naming_the_module(tmp_path):
    write_route(tmp_path, [(0, 0, 40), (400, 0, 40)])
    cfg = tmp_path / "cfg.toml"
    # (The kill is seen as the process's exit, not as silence: the heartbeat limit only has to
    # outlast ns-3's first network build, which holds the interpreter 2.5-3 s on the loaded
    # 2-core machine while cling compiles it.)
    cfg.write_text(flight(0.5, 2.0, "enb_position = [0.0, 0.0, 60.0]") + nats_transport(heartbeat_timeout=10.0))
    run = subprocess.Popen([os.path.join(BIN, "caviar-core"), "run", str(cfg), "--out", "run", "-q"], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        parts = tmp_path / "run" / "messages"
        deadline = time.monotonic() + 120
        while len(list(parts.glob("part-*.parquet")) if parts.exists() else []) < 3:
            assert run.poll() is None and time.monotonic() < deadline, run.communicate()
            time.sleep(0.1)
        out = subprocess.run(["ps", "-ww", "-eo", "pid,args"], capture_output=True, text=True).stdout
        (pid,) = [int(line.split()[0]) for line in out.splitlines()
                  if "caviar.worker" in line and "--module net " in line + " "]
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        _, err = run.communicate(timeout=60)
    finally:
        run.kill()
    assert time.monotonic() - killed < 10
    assert run.returncode == 1 and "module 'net' failed at step" in err and "signal: 9" in err, err


def _config_error(tmp_path, net: str) -> str:
    write_route(tmp_path, [(0, 0, 40), (40, 0, 40)])
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(flight(0.5, 10.0, net))
    with pytest.raises(caviar.ConfigError) as e:
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    return str(e.value)


def test_an_ns3_attribute_that_does_not_exist_is_refused_naming_the_key(tmp_path):
    msg = _config_error(tmp_path, 'attributes = { "ns3::LteUePhy::TxPowr" = 23 }')
    assert "cfg.toml:" in msg and 'modules.net.params.attributes."ns3::LteUePhy::TxPowr"' in msg, msg
    assert "no such attribute" in msg
    msg = _config_error(tmp_path, 'attributes = { "ns3::LteUePhy::TxPower" = "loud" }')
    assert '"ns3::LteUePhy::TxPower"' in msg and "'loud'" in msg and "expected a number" in msg, msg


def test_a_ran_the_wheel_does_not_build_is_refused_naming_the_key(tmp_path):
    msg = _config_error(tmp_path, 'ran = "nr"')
    assert "modules.net.params.ran" in msg and "5G-LENA" in msg and "lte, p2p" in msg, msg


def test_an_image_from_a_ue_without_a_node_stops_the_run_naming_the_key(tmp_path):
    write_route(tmp_path, [(0, 0, 40), (40, 0, 40)])
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(flight(0.5, 10.0, 'ues = ["uav2"]'))
    with pytest.raises(caviar.RunError) as e:
        with caviar.Simulation.from_toml(cfg, out=tmp_path / "run") as s:
            s.run(progress=False)
    msg = str(e.value)
    assert "'net'" in msg and "step 0" in msg and "modules.net.params.ues" in msg and "'uav1'" in msg, msg


def test_the_same_run_in_process_and_over_nats_records_the_same_messages(tmp_path, cli):
    """ns-3 is deterministic: a worker process of its own gives what the embedded plugin gave."""
    write_route(tmp_path, [(200, 0, 60), (500, 0, 60)])
    net = ('loss_from = "path"\nenb_position = [0.0, 0.0, 60.0]\n'
           'attributes = { "ns3::LteUePhy::EnableUplinkPowerControl" = false, "ns3::LteUePhy::TxPower" = 10 }')
    (tmp_path / "cfg.toml").write_text(flight(0.5, 20.0, net))
    cli("run", "cfg.toml", "-q", "--out", "inproc", check=0)
    cli("run", "cfg.toml", "-q", "--out", "nats", "--set", 'transport.kind="nats"', check=0)
    a, b = (caviar.load_run(tmp_path / d).messages.drop("seq") for d in ("inproc", "nats"))
    assert a.height == b.height > 100 and a.equals(b)
    quality = [m.data for m in caviar.load_run(tmp_path / "nats").decoded("ai.image_quality")]
    assert 0 < sum(d["complete"] for d in quality) < len(quality)  # in coverage, then out of it


def test_the_sar_mission_over_ns3_resumes_to_the_same_messages(tmp_path, cli):
    """ns-3's state is not saved: the journal of what the plugin did to it is, and replaying
    it on a new network after a SIGKILL gives the same packets, bit for bit."""
    from test_resume_plugins import _resumes_to_the_reference

    sets = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "--set",
            "modules.comm.params.raytracing.threads=1"]
    log = _resumes_to_the_reference(tmp_path, cli, ROOT / "blueprints" / "sar-ns3" / "config.toml", sets, kill=7,
                                    every=3, steps=12)
    quality = [m.data for m in log.decoded("ai.image_quality")]
    assert len(quality) == 12 and sum(d["complete"] for d in quality) >= 6
