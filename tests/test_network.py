"""The radio network (issue #23): cells, SINR with interference, A3 handover, and the
Sionna SYS link level, each checked against an independent computation."""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np
import pytest
import sionna.sys as sionna_sys  # the network extra, installed by scripts/setup.sh

import caviar
from caviar import _core
from caviar_plugins import DATA
from caviar_plugins.network.cells import (
    BOLTZMANN,
    ELEMENT_GAIN_DBI,
    element_gain_db,
    line_of_sight_gain_db,
    rx_power_dbm,
    sinr_db,
)
from caviar_plugins.network.handover import HandoverSettings, MobilityManager
from caviar_plugins.network.report import jain_index
from caviar_plugins.radio.link_level import LinkLevel
from caviar_plugins.radio.link_settings import DATA_SYMBOLS_PER_SLOT, LinkSettings
from caviar_plugins.radio.slot_results import RESULTS
from configs import episode, module, sionna_link
from conftest import write_config
from network_configs import (
    BAND,
    STAGES,
    assert_decides_as,
    canyon_scene,
    in_the_canyon,
    line_movers,
    mover,
    radio_network,
    ray_traced,
    reported,
    run_network,
    site,
    site_cells,
    top_level_torch_ops,
    ue_reports,
)

C = 299_792_458.0


def _two_cells_facing(d: float, height: float = 10.0):
    """Two one-sector sites 2d apart on the x axis, each pointing at the midpoint."""
    return site_cells(site("W", [-d, 0.0, height], [0.0]), site("E", [d, 0.0, height], [180.0]))


def test_two_equal_cells_give_0_db_and_one_alone_gives_friis_snr():
    cells = _two_cells_facing(100.0)
    ue = np.array([[0.0, 0.0, 10.0]])
    rx = rx_power_dbm(cells, line_of_sight_gain_db(cells, ue))
    # Both loaded, noise negligible (NF -200 dB): S = I.
    both = sinr_db(cells, rx, np.array([0]), noise_figure_db=-200.0)
    assert both[0] == pytest.approx(0.0, abs=1e-9)
    # The east cell off: SINR = SNR, computed here from Friis and k·T·B·NF.
    alone = sinr_db(cells, rx, np.array([0]), noise_figure_db=7.0, load=np.array([1.0, 0.0]))
    lam = C / 3.5e9
    friis_db = 20 * math.log10(lam / (4 * math.pi * 100.0))
    noise_dbm = 10 * math.log10(BOLTZMANN * 290.0 * 20e6 / 1e-3) + 7.0
    # Boresight, horizon: the element's full 8 dBi.
    assert alone[0] == pytest.approx(40.0 + ELEMENT_GAIN_DBI + friis_db - noise_dbm, abs=1e-9)
    # Half as far from the west cell: 6.02 dB more signal, and farther from the east one.
    ue = np.array([[-50.0, 0.0, 10.0]])
    rx = rx_power_dbm(cells, line_of_sight_gain_db(cells, ue))
    sir = sinr_db(cells, rx, np.array([0]), noise_figure_db=-200.0)[0]
    assert sir == pytest.approx(20 * math.log10(150.0 / 50.0), abs=1e-9)


def test_the_sector_pattern_follows_tr38901():
    cells = site_cells(site("S", [0.0, 0.0, 0.0], [0.0]))
    r = 100.0
    for phi, expected in [(0.0, 8.0), (32.5, 8.0 - 3.0), (65.0, 8.0 - 12.0), (180.0, 8.0 - 30.0)]:
        ue = np.array([[r * math.cos(math.radians(phi)), r * math.sin(math.radians(phi)), 0.0]])
        gain = element_gain_db(cells, ue)[0, 0]
        assert gain == pytest.approx(expected, abs=1e-9), phi


def _crossing(noise_db: float, seed: int, ms: float = 10.0):
    """RSRP of a UE driving from cell 0 to cell 1 at 10 m/s, with measurement noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 20.0, ms / 1e3)
    x = -100.0 + 10.0 * t  # crosses the border (x = 0) at t = 10 s
    d0, d1 = np.hypot(x + 200.0, 30.0), np.hypot(200.0 - x, 30.0)
    rsrp = np.stack([-60 - 20 * np.log10(d0), -60 - 20 * np.log10(d1)], axis=1)
    return t, rsrp + rng.normal(0.0, noise_db, size=rsrp.shape)


def _handovers(settings: HandoverSettings, noise_db: float, seed: int):
    mm = MobilityManager(settings, ["A/0", "B/0"])
    t, rsrp = _crossing(noise_db, seed)
    events = [e for k in range(len(t)) for e in mm.update(float(t[k]), "ue", list(rsrp[k]))]
    return [e for e in events if e["event"] == "handover"]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a3_hands_over_once_with_hysteresis_and_ping_pongs_without(seed):
    clean = _handovers(HandoverSettings(offset_db=0.0, hysteresis_db=3.0, time_to_trigger_s=0.16), 1.0, seed)
    assert len(clean) == 1, clean
    ho = clean[0]
    assert (ho["from_cell"], ho["to_cell"]) == ("A/0", "B/0")
    # Without noise, A3 (B better by Hys) starts to hold at t_a3 and the handover follows
    # a TTT later; noise (filtered) delays it by a little.
    t, exact = _crossing(0.0, seed)
    t_a3 = t[np.argmax(exact[:, 1] - 3.0 > exact[:, 0])]
    assert t_a3 + 0.16 - 1e-9 <= ho["time"] < t_a3 + 2.5, (ho, t_a3)
    assert _handovers(HandoverSettings(offset_db=0.0, hysteresis_db=3.0, time_to_trigger_s=0.16), 0.0,
                      seed)[0]["time"] == pytest.approx(t_a3 + 0.16, abs=0.05)  # the L3 filter lags
    bare = _handovers(HandoverSettings(offset_db=0.0, hysteresis_db=0.0, time_to_trigger_s=0.0), 1.0, seed)
    assert len(bare) > 3, bare
    assert bare[0]["time"] < ho["time"]


def test_a_link_below_q_out_for_t310_fails_and_reattaches():
    mm = MobilityManager(HandoverSettings(q_out_db=-8.0, t310_s=1.0), ["A/0", "B/0"])
    mm.update(0.0, "ue", [-80.0, -90.0], None)
    events = [e for k in range(1, 200) for e in mm.update(k * 0.01, "ue", [-80.0, -90.0], -10.0)]
    assert [e["event"] for e in events] == ["rlf"]
    assert events[0]["time"] == pytest.approx(1.01) and events[0]["to_cell"] == "A/0"


def test_a_ue_below_the_selection_threshold_is_out_of_coverage():
    mm = MobilityManager(HandoverSettings(min_rsrp_dbm=-130.0, l3_filter_k=0.0), ["A/0", "B/0"])
    assert mm.update(0.0, "far", [-140.0, -135.0]) == [] and mm.serving("far") == -1
    assert [e["event"] for e in mm.update(0.1, "far", [-120.0, -135.0])] == ["attach"]
    lost = mm.update(0.2, "far", [-131.0, -135.0])
    assert [(e["event"], e["from_cell"]) for e in lost] == [("coverage_lost", "A/0")] and mm.serving("far") == -1


@pytest.fixture(scope="module")
def link():
    return LinkLevel(LinkSettings(num_prb=51), n_cell=1, seed=7)


def test_the_bler_used_is_sionnas_nr_pdsch_table(link):
    path = pathlib.Path(sionna_sys.__file__).parent / "bler_tables" / "PDSCH_table1.json"
    table = json.loads(path.read_text())["category"]["1"]["index"]["1"]["MCS"]
    checked = 0
    for mcs, entry in table.items():
        for cbs, curve in entry["CBS"].items():
            # Points of the file that fall on the interpolation grid (0.1 dB, CBS 24 + 100·k).
            if (int(cbs) - 24) % 100:
                continue
            for snr, bler in zip(entry["SNR_db"], curve["BLER"], strict=True):
                if abs(round(snr * 10) - snr * 10) > 1e-6 or not 1e-3 < bler < 0.999:
                    continue
                assert link.table_bler(int(mcs), snr, int(cbs)) == pytest.approx(bler, rel=1e-4), (mcs, cbs, snr)
                checked += 1
    assert checked >= 20, checked


@pytest.mark.parametrize("processes", [1, 8])
def test_outer_loop_link_adaptation_reaches_its_bler_target(processes):
    for target in (0.1, 0.3):
        ll = LinkLevel(LinkSettings(num_prb=51, bler_target=target, harq_processes=processes), n_cell=1, seed=11)
        rng = np.random.default_rng(5)
        slots = 2000 * (1 if processes == 1 else 4)  # each process's own loop sees 1 slot in D
        sinr = 12.0 + rng.normal(0.0, 1.0, size=(slots, 1))  # a noisy channel
        res = ll.run(sinr, np.array([0]))
        assert res.acks[0] + res.nacks[0] == slots
        assert res.bler(0) == pytest.approx(target, abs=0.02), (target, processes, res.bler(0))


def test_the_compiled_link_level_decides_as_eager_and_reaches_the_bler_target():
    """``compile = true`` (torch.compile): on the same frequency-selective SINRs the first
    call's MCS, effective SINR, TBLER and PRBs are eager's exactly; the HARQ outcomes come
    from another random stream, and the outer loop still brings the BLER to its target."""
    rng = np.random.default_rng(6)
    d, sub = 8, 4
    sinr = 14.0 + rng.normal(0.0, 3.0, size=(d, 3, sub))
    serving = np.zeros(3, dtype=int)
    settings = LinkSettings(num_prb=51, harq_processes=d, subbands=sub)
    eager = LinkLevel(settings, n_cell=1, seed=11).run(sinr, serving)
    compiled_ll = LinkLevel(dataclasses.replace(settings, compile=True), n_cell=1, seed=11)
    assert_decides_as(compiled_ll.run(sinr, serving), eager)
    # The whole group of slots is one compiled program: few torch operations run outside it (on a
    # GPU, each a kernel launch), where eager runs hundreds: what a group adds, calls of 1 and 11 groups.
    compiled_ll.run(sinr, serving)  # (its second call compiles once more: the blocks are built)
    longer = np.concatenate([sinr] * 11)
    per_group = {name: (top_level_torch_ops(lambda ll=ll: ll.run(longer, serving))
                        - top_level_torch_ops(lambda ll=ll: ll.run(sinr, serving))) / 10
                 for name, ll in (("eager", LinkLevel(settings, n_cell=1, seed=11)), ("compiled", compiled_ll))}
    assert per_group["compiled"] <= 20 < 300 <= per_group["eager"], per_group
    slots = 8000  # each of the 8 processes' loops sees 1000
    res = compiled_ll.run(12.0 + rng.normal(0.0, 1.0, size=(slots, 3, sub)), serving)
    assert (res.acks + res.nacks).sum() >= slots  # someone is served in every slot
    bler = res.nacks.sum() / (res.acks + res.nacks).sum()
    assert bler == pytest.approx(0.1, abs=0.02), bler


def test_a_settled_compiled_link_level_checks_fewer_guards_and_decides_the_same(monkeypatch):
    """After ``CHECKED_CALLS`` calls of its compiled group at a capacity, a link level lets dynamo
    check only the guards that tell its entries apart: every result of the calls after it is the
    same, bit for bit, as a twin's that checks every guard; where torch refuses to compile in that
    stance, the group runs again under every guard (the same results), and the count starts again,
    as it does when the link level grows."""
    from caviar_plugins.radio import link_level

    rng = np.random.default_rng(8)
    d, sub = 8, 4
    settings = LinkSettings(num_prb=51, harq_processes=d, subbands=sub, compile=True)
    serving = np.zeros(3, dtype=int)
    calls = [14.0 + rng.normal(0.0, 3.0, size=(3 * d, 3, sub)) for _ in range(5)]  # 3 groups a call
    results = {}
    for name, checked in (("every guard", 10**9), ("settled", link_level.CHECKED_CALLS)):
        monkeypatch.setattr(link_level, "CHECKED_CALLS", checked)
        ll = LinkLevel(settings, n_cell=1, seed=11)
        results[name] = [ll.run(sinr, serving) for sinr in calls[:4]]
        assert ll._settled() == (name == "settled"), name  # (12 calls made, 8 checked in full)
        inner, calls_made = ll._group, []

        def refused_once(*args, inner=inner, calls_made=calls_made):  # (the second group of the last call)
            calls_made.append(args)
            if len(calls_made) == 2:
                raise RuntimeError("Recompilation triggered with skip_guard_eval_unsafe stance (a test's)")
            return inner(*args)
        if name == "settled":
            ll._group = refused_once
        results[name].append(ll.run(calls[4], serving))
        if name == "settled":
            assert len(calls_made) == 4 and not ll._settled()  # (3 groups, one twice; counting again)
    for full, fewer in zip(*results.values(), strict=True):
        for name in RESULTS:
            np.testing.assert_array_equal(getattr(fewer, name), getattr(full, name), err_msg=name)
    ll._checked = link_level.CHECKED_CALLS
    assert ll._settled()
    ll.ensure(ll.capacity + 1)  # (new blocks: every guard again)
    assert not ll._settled()


def test_a_second_compiled_link_level_compiles_nothing_and_decides_as_the_first():
    """Link levels of the same settings share their compiled group of slots (until 2026-11-29
    each made its own PHY abstraction class, and compiled again): a second one, with its own
    blocks, compiles nothing (torch's ``fail_on_recompile`` stance) and, from the same seed,
    decides as the first did, bit for bit."""
    import torch

    rng = np.random.default_rng(9)
    settings = LinkSettings(num_prb=51, harq_processes=8, subbands=4, compile=True)
    serving = np.zeros(3, dtype=int)
    calls = [14.0 + rng.normal(0.0, 3.0, size=(16, 3, 4)) for _ in range(2)]
    first = LinkLevel(settings, n_cell=1, seed=11)
    before = [first.run(sinr, serving) for sinr in calls]  # (compiles: before and after the blocks are built)
    second = LinkLevel(settings, n_cell=1, seed=11)
    with torch.compiler.set_stance("fail_on_recompile"):
        after = [second.run(sinr, serving) for sinr in calls]
    for a, b in zip(before, after, strict=True):
        for name in RESULTS:
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)


def test_harq_processes_give_the_same_throughput_faster_in_calls():
    """D slots per call, each its own HARQ process: the long-run throughput of a cell stays
    within 3 % of the slot-by-slot loop's on the same channels."""
    rng = np.random.default_rng(2)
    sinr = rng.uniform(0.0, 25.0, size=(4000, 6))
    serving = np.array([0, 0, 0, 1, 1, 1])
    rates = []
    for processes in (1, 8):
        ll = LinkLevel(LinkSettings(num_prb=51, harq_processes=processes), n_cell=2, seed=4)
        rates.append(ll.run(sinr, serving).decoded_bits.sum())
    assert rates[1] == pytest.approx(rates[0], rel=0.03), rates
    with pytest.raises(ValueError, match="harq_processes = 8"):
        LinkLevel(LinkSettings(num_prb=51, harq_processes=8), n_cell=1).run(np.zeros((12, 1)), np.array([0]))


def _schedule(scheduler: str, sinr_db_ue: np.ndarray, slots: int = 400, fading: bool = False):
    """Throughputs under ``scheduler``; with ``fading``, Rayleigh block fading per slot
    (the same draws for every scheduler)."""
    sinr = np.tile(sinr_db_ue, (slots, 1))
    if fading:
        sinr = sinr + 10 * np.log10(np.random.default_rng(9).exponential(size=sinr.shape))
    ll = LinkLevel(LinkSettings(num_prb=51, scheduler=scheduler), n_cell=1, seed=3)
    res = ll.run(sinr, np.zeros(sinr_db_ue.size, dtype=int))
    return res, res.throughput_bps(slots, ll.s.slot_s)


def test_proportional_fair_is_fairer_than_max_rate_and_faster_than_round_robin():
    sinr = np.array([0.0, 5.0, 10.0, 18.0, 25.0])
    _, pf = _schedule("proportional-fair", sinr, fading=True)
    _, mr = _schedule("max-rate", sinr, fading=True)
    _, rr = _schedule("round-robin", sinr, fading=True)
    assert jain_index(pf) > jain_index(mr) + 0.1, (pf, mr)
    # Multi-user diversity: PF serves each UE near its own fading peaks.
    assert pf.sum() > rr.sum() * 1.1, (pf.sum(), rr.sum())
    assert (pf > 0).all()


def test_no_ue_gets_more_than_the_shannon_bound_of_its_sinr():
    sinr = np.array([-3.0, 2.0, 8.0, 15.0, 22.0, 28.0])
    res, _ = _schedule("proportional-fair", sinr, slots=300)
    # Shannon per channel use: each data resource element carries at most log2(1 + SINR) bits.
    data_re = res.prbs * 12 * DATA_SYMBOLS_PER_SLOT
    bound = data_re * np.log2(1 + 10 ** (sinr / 10))
    assert (res.decoded_bits <= bound).all(), (res.decoded_bits, bound)
    assert (res.decoded_bits > 0.3 * bound).all()


NETWORK = (episode(0.02, STAGES, seed=4, duration=24.0)
           + line_movers(mover("car1", [-150.0, 20.0, 1.5], [150.0, 20.0, 1.5], 12.5),
                         mover("ped1", [-160.0, -20.0, 1.5], [-160.0, -25.0, 1.5], 1.0, type="pedestrian"))
           + radio_network([site("west", [-200.0, 0.0, 25.0], [0.0, 120.0, 240.0]),
                            site("east", [200.0, 0.0, 25.0], [180.0, 300.0, 60.0])],
                           **BAND, subcarrier_spacing_hz=15e3,
                           # a step's 20 slots in 2 calls of Sionna SYS (slot by slot: 10x the calls, the same handover)
                           harq_processes=10,
                           handover={"offset_db": 0.0, "hysteresis_db": 3.0, "time_to_trigger_s": 0.16}))


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")  # outputs recorded only
def test_a_car_crossing_between_two_sites_hands_over_once_in_the_loop(tmp_path):
    log = run_network(tmp_path, NETWORK)
    events = [m.data for m in log.decoded("network.events")]
    kinds = [(e["event"], e["UE_Id"]) for e in events]
    assert kinds.count(("attach", "car1")) == 1 and kinds.count(("attach", "ped1")) == 1
    hos = [e for e in events if e["event"] == "handover"]
    assert [(e["UE_Id"], e["from_cell"], e["to_cell"]) for e in hos] == [("car1", "west/0", "east/0")], hos
    car = [u for u in ue_reports(log) if u["UE_Id"] == "car1"]
    assert {u["serving_cell"] for u in car} == {"west/0", "east/0"}
    assert all(0 <= u["mcs"] <= 28 and u["throughput_mbps"] > 0 for u in car[5:])  # NR table 1: MCS 0-28
    # The paper's schema keeps working.
    thr = [m.data for m in log.decoded("communications.throughput")]
    assert {t["UE_Id"] for t in thr} == {"car1", "ped1"} and all(t["throughput"] >= 0 for t in thr)
    # Where both cells reach the car equally (equal RSRP), the interferer's beam serves its
    # own UEs: the SINR is the 4×4 array gain, 10·log10(16) dB, less the other sectors and noise.
    border = min(car, key=lambda u: abs(u["rsrp_dbm"]["west/0"] - u["rsrp_dbm"]["east/0"]))
    assert 10 * math.log10(16) - 1.0 < border["sinr_db"] <= 10 * math.log10(16), border

    # caviar-core report draws the CDFs and the handover map; its numbers are the log's.
    rep = reported(tmp_path)
    for name in ("network-cdf.png", "network-handovers.png", "modules.png"):
        assert (rep / name).stat().st_size > 10_000, name
    numbers = json.loads((rep / "network.json").read_text())
    car_sinr = np.array([u["sinr_db"] for u in car])
    assert numbers["ue_types"]["car"]["sinr_db"]["p50"] == pytest.approx(np.percentile(car_sinr, 50), abs=1e-3)
    assert numbers["ue_types"]["car"]["handovers"] == 1 and numbers["ue_types"]["pedestrian"]["handovers"] == 0
    assert max(u["sinr_db"] for u in car) > 15.0


@pytest.mark.parametrize("edit, key", [
    ('name = "east"', "sites.1.name"),  # two sites named west
    ('azimuths_deg = [180.0, 300.0, 60.0]', "sites.1.array"),
    ("subcarrier_spacing_hz = 15000.0", "mcs_table"),
    ("subcarrier_spacing_hz = 15000.0", "bler_target"),
    ("carrier_hz = 3500000000.0", "carrier_hz"),
    ("bandwidth_hz = 20000000.0", "num_prb"),
    # Nested tables are typed (HandoverSettings, TraceSettings): checked recursively, the whole key path named.
    ("time_to_trigger_s = 0.16", "handover.time_to_triger_s"),  # unknown key
    ("hysteresis_db = 3.0", "handover.hysteresis_db"),  # its own check
    ("offset_db = 0.0", "handover.offset_db"),  # wrong type
    ("handover = {", "raytracing.max_depth"),
    ("handover = {", "raytracing"),  # not a table
])
def test_bad_network_input_names_the_key_before_anything_runs(tmp_path, capfd, edit, key):
    replacement = {
        "sites.1.name": 'name = "west"',
        "sites.1.array": 'azimuths_deg = [180.0, 300.0, 60.0]\narray = [0, 4]',
        "mcs_table": "subcarrier_spacing_hz = 15e3\nmcs_table = 7",
        "bler_target": "subcarrier_spacing_hz = 15e3\nbler_target = 1.5",
        "carrier_hz": "carrier_hz = 12e9",
        "num_prb": "bandwidth_hz = 21e6",
        "handover.time_to_triger_s": "time_to_triger_s = 0.16",
        "handover.hysteresis_db": "hysteresis_db = -1.0",
        "handover.offset_db": 'offset_db = "high"',
        "raytracing.max_depth": "raytracing = { max_depth = -1 }\nhandover = {",
        "raytracing": 'raytracing = "ray-traced"\nhandover = {',
    }[key]
    cfg = tmp_path / "net.toml"
    text = NETWORK.replace(edit, replacement, 1)
    cfg.write_text(text)
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert f"modules.net.params.{key}" in first, first
    if key != "num_prb":  # the others are written in the file: their line is named
        last = replacement.splitlines()[0 if key.startswith("raytracing") else -1]
        line = text[:text.rindex(last)].count("\n") + 1
        assert f"{cfg}:{line}: " in first, (line, first)


def test_ray_traced_gains_equal_friis_and_the_pattern_in_free_space():
    """A ray test: in an empty scene only the direct path exists, so the traced gain of
    every sector is Friis times its pattern along the straight line (an independent
    computation), for sites traced together in one solve."""
    from caviar_plugins.network.raytraced import NETWORK_RAYS, SiteTracer

    cells = site_cells(site("A", [0.0, 0.0, 30.0], [0.0, 120.0, 240.0], 6.0), site("B", [300.0, 50.0, 20.0], [200.0]))
    ues = np.array([[120.0, 40.0, 1.5], [-80.0, -60.0, 1.5], [250.0, 300.0, 40.0]])
    tracer = SiteTracer("empty", dataclasses.replace(NETWORK_RAYS, max_depth=0, samples_per_src=1000), cells)
    for placed in (ues, ues[:2] + 10.0):  # (then the UEs move: the same receivers, new positions)
        traced = tracer.gains_db(placed)
        assert traced.shape == (len(placed), 4)
        np.testing.assert_allclose(traced, line_of_sight_gain_db(cells, placed), atol=1e-3)


def _canyon_tracer(max_depth: int = 2):
    """One sector at the west end of Sionna's simple street canyon, looking down the street."""
    import sionna.rt as rt

    from caviar_plugins.network.raytraced import NETWORK_RAYS, SiteTracer

    cells = site_cells(site("W", [-80.0, 0.0, 10.0], [0.0]))
    rays = dataclasses.replace(NETWORK_RAYS, max_depth=max_depth, samples_per_src=20_000)
    return cells, SiteTracer(rt.scene.simple_street_canyon, rays, cells, seed=2)


def test_traced_doppler_is_v_cos_theta_over_lambda_for_the_direct_and_the_floor_path():
    """The traced paths' Doppler shifts (from their directions of arrival) against
    f_D = v·û/λ along the direct path and along the floor reflection (û toward the
    transmitter's image below the floor): an independent computation with the speed of
    light, as is each path's delay."""
    cells, tracer = _canyon_tracer(max_depth=1)
    ue, v = np.array([0.0, 2.0, 1.5]), np.array([10.0, 3.0, 0.0])
    ch = tracer.trace(ue[None])
    doppler = ch.doppler_hz(v[None])
    lam = C / 3.5e9
    tx = np.array(cells[0].position)
    floor_z = float(tracer.scene.objects["floor"].mi_mesh.bbox().min[2])
    for source in (tx, np.array([tx[0], tx[1], 2 * floor_z - tx[2]])):
        d = source - ue
        k = int(np.argmin(np.abs(ch.delay_s[0, 0] - np.linalg.norm(d) / C)))
        assert ch.delay_s[0, 0, k] == pytest.approx(np.linalg.norm(d) / C, rel=1e-5)
        assert doppler[0, 0, k] == pytest.approx(v @ d / np.linalg.norm(d) / lam, rel=1e-4)
    assert np.abs(ch.doppler_hz(np.zeros((1, 3)))).max() == 0.0  # at rest: no shift


def test_the_channel_between_traces_evolves_as_a_new_trace_sees_it():
    """Between two traces every path's phase turns with its Doppler shift. A UE moving at
    10 m/s down a street canyon (many paths, a fading channel): the channel evolved for
    t seconds agrees, subband by subband, with a fresh trace at the moved position (within
    5 % of the band's mean power while it moves up to 1.2 wavelengths), where a frozen channel is
    off by more than half of it."""
    _, tracer = _canyon_tracer()
    ue, v = np.array([[0.0, 2.0, 1.5]]), np.array([[10.0, 0.0, 0.0]])
    ch = tracer.trace(ue)
    assert (np.abs(ch.amplitude[0, 0]) > 0).sum() >= 8
    f = LinkSettings(num_prb=106, subcarrier_spacing_hz=15e3, subbands=8).subband_frequencies_hz
    held = 10 ** (ch.gain_db(ue, f)[0, 0] / 10)
    assert 10 * np.log10(held.max() / held.min()) > 3.0  # frequency-selective: the paths' delays differ
    frozen_error = 0.0
    for t in (0.002, 0.005, 0.01):
        evolved = 10 ** (ch.gain_db(ue + v * t, f)[0, 0] / 10)
        fresh = 10 ** (tracer.trace(ue + v * t).gain_db(ue + v * t, f)[0, 0] / 10)
        # Errors relative to the band's mean power (a deep fade's dB are not a fair yardstick).
        assert np.abs(evolved - fresh).max() / fresh.mean() < 0.05, (t, evolved, fresh)
        frozen_error = max(frozen_error, float(np.abs(held - fresh).max() / fresh.mean()))
    assert frozen_error > 0.5, frozen_error


def test_subbands_with_equal_sinr_give_what_one_wideband_resource_gives():
    """A flat channel in 4 subbands is the wideband channel: the scheduler gives every
    subband to the same UE, the EESM of equal SINRs is that SINR, and the decoded bits,
    PRBs and HARQ outcomes are the same (same seed)."""
    sinr = np.tile([6.0, 12.0, 20.0], (200, 1))
    serving = np.zeros(3, dtype=int)
    wide = LinkLevel(LinkSettings(num_prb=51), n_cell=1, seed=5).run(sinr, serving)
    sub = LinkLevel(LinkSettings(num_prb=51, subbands=4), n_cell=1, seed=5).run(
        np.repeat(sinr[..., None], 4, axis=2), serving)
    np.testing.assert_array_equal(sub.prbs, wide.prbs)
    np.testing.assert_array_equal(sub.acks + sub.nacks, wide.acks + wide.nacks)
    np.testing.assert_allclose(sub.decoded_bits, wide.decoded_bits, rtol=0.05)


def test_proportional_fair_per_subband_serves_each_ue_where_its_channel_is_strong():
    """Two UEs with opposite frequency-selective channels: UE 0 strong in the lower half
    of the band, UE 1 in the upper half. PF per subband gives each mostly its strong half,
    beats giving each the whole band in turn (round robin), and no UE decodes more than the
    Shannon bound of the PRBs it was given."""
    low, high = 22.0, 2.0
    sinr = np.array([[low] * 4 + [high] * 4, [high] * 4 + [low] * 4])  # [ue, subband]
    slots = 400
    block = np.tile(sinr, (slots, 1, 1))
    settings = LinkSettings(num_prb=48, subbands=8, harq_processes=4)
    ll = LinkLevel(settings, n_cell=1, seed=8)
    torch = ll._torch
    granted: list = []
    schedule = ll._schedule
    ll._schedule = lambda *a: granted.append(schedule(*a)) or granted[-1]  # record the decisions
    res = ll.run(block, np.zeros(2, dtype=int))
    g = torch.cat([x[0] for x in granted]).numpy()[:, 0, :, :2]  # [slot, subband, ue] (of the one link)
    assert g[:, :4, 0].mean() > 0.8 and g[:, 4:, 1].mean() > 0.8, g.mean(axis=0)
    # Each UE on the whole band in turn (round robin) on the same channels: the EESM of a
    # band half in a fade is far below the strong half's SINR.
    turns = LinkLevel(dataclasses.replace(settings, scheduler="round-robin"), n_cell=1, seed=8).run(
        block, np.zeros(2, dtype=int))
    assert res.decoded_bits.sum() > 1.3 * turns.decoded_bits.sum(), (res.decoded_bits, turns.decoded_bits)
    bound = slots * 12 * DATA_SYMBOLS_PER_SLOT * (settings.subband_prbs * np.log2(1 + 10 ** (sinr / 10))).sum(axis=1)
    assert (res.decoded_bits <= bound).all()


@pytest.mark.filterwarnings("ignore::caviar.simulation.WiringWarning")  # outputs recorded only
def test_in_the_loop_the_ray_traced_sinr_fades_between_refreshes(tmp_path):
    """In a run: the car's SINR changes from step to step between two traces (refresh
    every 0.5 s, steps of 20 ms, 30 cm) as its paths' phases turn; with evolve = "hold"
    it is constant between traces."""
    def sinrs(evolve: str) -> np.ndarray:
        text = in_the_canyon(duration=1.0, subcarrier_spacing_hz=30e3, harq_processes=8, subbands=8, **ray_traced(
            canyon_scene(), max_depth=2, samples_per_src=20000, refresh_s=0.5, mode=evolve))
        ue = ue_reports(run_network(tmp_path, text, evolve, f"{evolve}.toml"))
        assert len(ue) == 50 and all(u["serving_cell"] == "west/0" for u in ue)
        return np.array([u["sinr_db"] for u in ue])

    held, evolved = sinrs("hold"), sinrs("doppler")
    # Steps 0-24 share the trace of step 0.
    assert np.ptp(held[:25]) == 0.0
    assert np.ptp(evolved[:25]) > 1.0 and len(np.unique(evolved[:25])) > 20


def test_the_radio_map_matches_friis_and_the_pattern_and_picks_the_facing_sector(tmp_path):
    """Sionna's radio-map solver with its tr38901 element, in free space: the path gain
    of each of a site's three sectors equals Friis times the sector pattern computed here
    (Monte Carlo noise aside), and the best server is the sector facing the point."""
    from caviar_plugins.network.radio_map import MAP_RAYS, RadioMapSettings, best_server_map, save

    cells = site_cells(site("A", [0.0, 0.0, 30.0], [0.0, 120.0, 240.0], 6.0))
    flat = RadioMapSettings(cell_size_m=10.0, margin_m=200.0, raytracing=dataclasses.replace(MAP_RAYS, max_depth=0))
    res = best_server_map(cells, flat, "empty", num_prb=106, noise_figure_db=7.0)
    x, y = np.meshgrid(res["x"], res["y"])
    points = np.stack([x.ravel(), y.ravel(), np.full(x.size, 1.5)], axis=1)
    expected = line_of_sight_gain_db(cells, points).T.reshape(res["gain_db"].shape)
    away = np.hypot(x, y) > 50.0
    err = (res["gain_db"] - expected)[:, away]
    assert np.median(np.abs(err)) < 0.5 and abs(err.mean()) < 0.25, (np.median(np.abs(err)), err.mean())
    azimuth = np.degrees(np.arctan2(y, x))
    facing = np.argmin([np.abs((azimuth - a + 180.0) % 360.0 - 180.0) for a in (0.0, 120.0, 240.0)], axis=0)
    off_border = np.min([np.abs((azimuth - b + 180.0) % 360.0 - 180.0) for b in (60.0, 180.0, 300.0)], axis=0) > 10
    assert (res["best"] == facing)[away & off_border].mean() > 0.99
    # One site's sectors interfere with each other: the SINR is highest on boresight.
    assert np.nanmax(res["sinr_db"]) > 10.0 and np.all(np.isfinite(res["sinr_db"][away]))
    npz, png, layer = save(res, cells, tmp_path)
    assert layer.name == "radio-map-layer.png"
    assert list(np.load(npz)["cells"]) == ["A/0", "A/1", "A/2"] and png.stat().st_size > 10_000


def test_sionna_link_with_the_sys_link_model(tmp_path):
    """The SAR's communications module with ``link_model = "sys"``: two UAVs share the
    cell; each decodes at most log2(1 + SNR) bits per data resource element it was given,
    with the SNR of its used beam pair, and the paper's throughput schema stays."""
    route = (DATA / "central_park_path0_scene.csv").as_posix()
    cfg = write_config(tmp_path, episode(0.1, STAGES, steps=3, seed=5)
                       + module("uav", "mobility", "waypoint-flight", {"waypoints": route, "frame": "scene",
                                                                       "ue_id": "uav1"})
                       + module("uav2", "mobility", "waypoint-flight", {"waypoints": route, "frame": "scene",
                                                                        "ue_id": "uav2", "speed": 10.0})
                       + sionna_link(link_model="sys", publish_channels=False))
    log = caviar.Simulation.from_toml(cfg, out=tmp_path / "run").run()
    links = [m.data for m in log.decoded("communications.link")]
    thr = [m.data for m in log.decoded("communications.throughput")]
    assert [t["UE_Id"] for t in thr] == ["uav1", "uav2"] * 3
    slots = round(0.1 / 0.000125)  # 120 kHz: 0.125 ms slots
    for link, t in zip(links, thr, strict=True):
        assert link["link_model"] == "sys" and 0 <= link["mcs"] <= 28 and link["harq_ack"] + link["harq_nack"] >= 0
        bits = t["throughput"] * 1e6 * 0.1
        bound = link["prbs"] * 12 * DATA_SYMBOLS_PER_SLOT * math.log2(1 + 10 ** (link["snr_db"] / 10))
        assert bits <= bound + 1e-6, (link, t)
    # The two share the cell's PRB-slots: 27 PRBs (40 MHz at 120 kHz) x 800 slots per step.
    for step in range(3):
        assert sum(link["prbs"] for link in links[2 * step:2 * step + 2]) == 27 * slots
    bad = tmp_path / "bad.toml"
    bad.write_text(cfg.read_text().replace('link_model = "sys"', 'link_model = "sys", protocol = "paper"'))
    assert _core.main(["caviar-core", "validate", str(bad)]) == 2
