"""The radio network's step without per-UE host work (issue #53, part 4): the mobility
manager's one update for all UEs against the per-UE rules written out by hand, the UE table's
columns, the reports built in bulk against per-UE rounding, a slot-broadcast SINR against its
copy, and the compiled link level's CUDA-graph option (its resolution, and on the CPU the same
numbers as eager)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from caviar_plugins.network.handover import HandoverSettings, MobilityManager
from caviar_plugins.network.report import finite
from caviar_plugins.network.ues import (
    UeTable,
    rounded,
    rounded_array,
    ue_reports,
    uplink_arrays,
    uplink_columns,
    uplink_fields,
)
from caviar_plugins.radio.link_level import LinkLevel
from caviar_plugins.radio.link_settings import LinkSettings, cuda_graphs_on
from network_configs import assert_decides_as


def _by_hand(s: HandoverSettings, names, state: dict, t: float, ue: str, rsrp: list[float], sinr):
    """TS 38.331's rules for one UE, one measurement, as plain Python (the manager's before #53)."""
    st = state.get(ue)
    if st is not None:
        a = 0.5 ** (s.l3_filter_k / 4)
        rsrp = [(1 - a) * f + a * m for f, m in zip(st["filtered"], rsrp, strict=True)]

    def event(kind, old, new):
        ev = {"event": kind, "UE_Id": ue, "time": round(t, 9), "to_cell": names[new],
              "rsrp_to_dbm": round(rsrp[new], 3)}
        if old is not None:
            ev.update(from_cell=names[old], rsrp_from_dbm=round(rsrp[old], 3))
        return ev
    best = max(range(len(rsrp)), key=lambda c: rsrp[c])
    if rsrp[best] < s.min_rsrp_dbm:
        if st is None:
            return []
        del state[ue]
        ev = event("coverage_lost", st["serving"], best)
        del ev["to_cell"], ev["rsrp_to_dbm"]
        return [ev]
    fresh = {"candidate": -1, "since": 0.0, "below": None, "filtered": list(rsrp)}
    if st is None:
        state[ue] = {"serving": best, **fresh}
        return [event("attach", None, best)]
    st["filtered"] = list(rsrp)
    if sinr is not None and sinr < s.q_out_db:
        if st["below"] is None:
            st["below"] = t
        elif t - st["below"] >= s.t310_s - 1e-9:
            state[ue] = {"serving": best, **fresh}
            return [{**event("rlf", st["serving"], best), "sinr_db": round(sinr, 3)}]
    else:
        st["below"] = None
    _a3_by_hand(s, st, t, rsrp)
    if st["candidate"] >= 0 and t - st["since"] >= s.time_to_trigger_s - 1e-9:
        state[ue] = {"serving": st["candidate"], **fresh}
        return [event("handover", st["serving"], st["candidate"])]
    return []


def _a3_by_hand(s: HandoverSettings, st: dict, t: float, rsrp: list[float]) -> None:
    """A3's entering condition: the timer runs for the best neighbour meeting it."""
    entering = [c for c in range(len(rsrp)) if c != st["serving"]
                and rsrp[c] - s.hysteresis_db > rsrp[st["serving"]] + s.offset_db]
    if not entering:
        st["candidate"] = -1
    elif st["candidate"] != (top := max(entering, key=lambda c: rsrp[c])):
        st["candidate"], st["since"] = top, t


@pytest.mark.parametrize("k", [4.0, 0.0])
def test_one_update_of_all_ues_is_the_per_ue_rules(k):
    """60 UEs × 5 cells over 120 measurements (drifting RSRP with noise, a few far enough to
    lose coverage, SINRs below q_out at times, UEs in shuffled rows): the same events in the
    same order, and the same serving cells, as the rules applied UE by UE."""
    rng = np.random.default_rng(3)
    s = HandoverSettings(offset_db=1.0, hysteresis_db=1.0, time_to_trigger_s=0.08, t310_s=0.2, l3_filter_k=k)
    names = [f"c{c}" for c in range(5)]
    n = 60
    rows = rng.permutation(200)[:n]  # (columns need not be 0..n-1)
    ids = [f"ue{i}" for i in range(n)]
    base = rng.uniform(-125, -70, size=(n, 5))
    drift = rng.normal(0, 0.4, size=(n, 1)) + rng.normal(0, 0.3, size=(n, 5))  # (some fade out, then back)
    level = rng.uniform(-16, 6, n)  # (each UE's SINR)
    mm, state = MobilityManager(s, names), dict[str, dict]()
    kinds = set()
    for step in range(120):
        t = step * 0.02
        rsrp = base + drift * (60 - abs(step - 60)) + rng.normal(0, 2.0, size=(n, 5))
        sinr = np.where(rng.random(n) < 0.9, level + rng.normal(0, 2, n), np.nan)
        got = mm.update_rows(t, rows, ids, rsrp, sinr)
        want = [e for i in range(n) for e in _by_hand(s, names, state, t, ids[i], rsrp[i].tolist(),
                                                      None if np.isnan(sinr[i]) else float(sinr[i]))]
        assert got == want, step
        by_hand = [state[u]["serving"] if u in state else -1 for u in ids]
        np.testing.assert_array_equal(mm.serving_cell[rows], by_hand)
        kinds |= {e["event"] for e in got}
    assert kinds == {"attach", "handover", "rlf", "coverage_lost"}, kinds  # (every rule ran)


def test_the_per_name_api_and_the_state_round_trip():
    mm = MobilityManager(HandoverSettings(), ["A", "B"])
    assert [e["event"] for e in mm.update(0.0, "u", [-80.0, -90.0])] == ["attach"] and mm.serving("u") == 0
    saved = mm.state()
    mm.forget("u")
    assert mm.serving("u") == -1
    mm.restore(saved)
    assert mm.serving("u") == 0 and mm.update(0.1, "u", [-80.0, -90.0]) == []
    mm.ensure(20)  # (rows for more UEs: the old kept, the new unattached)
    assert mm.serving("u") == 0 and len(mm.serving_cell) >= 20 and (mm.serving_cell[1:20] == -1).all()


def test_the_ue_table_reuses_columns_and_starts_them_afresh():
    table = UeTable()
    cols = [table.add(f"u{i}", "car") for i in range(10)]  # (past the first 8: the arrays grow)
    assert cols == list(range(10)) and table.position.shape == (16, 3)
    table.position[3], table.last_sinr[3] = (1.0, 2.0, 3.0), 7.0
    ids, c, types = table.view()
    assert table.view()[0] is ids and list(c) == cols and types == ["car"] * 10
    assert table.pop("u3") == 3 and table.view()[0] is not ids
    assert table.add("new", "uav") == 3  # the first free column, its numbers reset
    assert table.position[3].tolist() == [0, 0, 0] and np.isnan(table.last_sinr[3])
    assert table.view()[0][-1] == "new" and table.view()[2][-1] == "uav"


def test_reports_built_in_bulk_round_as_one_by_one():
    """``network.ue`` and the throughput from arrays: rounding as ``round(float(x), n)`` and
    ``finite`` give it element by element, None for a UE without a cell or a non-finite SINR."""
    rng = np.random.default_rng(5)
    n, names = 4, ["a", "b", "c"]
    serving = np.array([0, -1, 2, 1])
    sinr, sir = rng.normal(5, 9, n), rng.normal(9, 9, n)
    sinr[3] = -np.inf
    loss, rsrp, mbps = rng.uniform(80, 130, n), rng.uniform(-120, -60, (n, 3)), rng.uniform(0, 40, n)
    link = {"mcs": np.array([3, -1, 9, 0]), "tbler": np.array([0.123456, np.nan, 0.0, 1.0]),
            "harq_ack": np.array([4, 0, 5, 0]), "harq_nack": np.array([1, 0, 0, 2]), "prbs": np.array([9, 0, 3, 1])}
    listed = np.sort(np.argsort(-rsrp, axis=1, kind="stable")[:, :2], axis=1)
    types = ["car", "uav", "dropped", "car"]
    out = list(ue_reports(names, ["u0", "u1", "u2", "u3"], types, serving, sinr, sir, loss, rsrp, listed, mbps,
                          link, lambda i, covered: {"x": i} if covered else {}, rng.uniform(0, 9, (n, 3))))
    assert [topic for topic, _ in out] == ["communications.throughput", "network.ue"] * n
    for i in range(n):
        thr, rep = out[2 * i][1], out[2 * i + 1][1]
        assert thr == {"UE_type": types[i], "UE_Id": f"u{i}", "throughput": round(float(mbps[i]), 6)}
        covered = serving[i] >= 0
        assert rep["serving_cell"] == (names[serving[i]] if covered else None)
        assert rep["sinr_db"] == (finite(sinr[i]) if covered else None)
        assert rep["sir_db"] == (finite(sir[i]) if covered else None)
        assert rep["coupling_loss_db"] == (round(float(loss[i]), 3) if covered else None)
        assert rep["rsrp_dbm"] == {names[k]: round(float(rsrp[i, k]), 2) for k in sorted(listed[i].tolist())}
        assert rep["mcs"] == int(link["mcs"][i]) and type(rep["mcs"]) is int
        assert rep["tbler"] == (None if math.isnan(link["tbler"][i]) else round(float(link["tbler"][i]), 4))
        assert ("x" in rep) == covered and ("position_m" in rep) == (types[i] == "dropped")
    assert out[3][1]["sinr_db"] is None and list(out[1][1])[:8] == [
        "UE_type", "UE_Id", "serving_cell", "sinr_db", "sir_db", "coupling_loss_db", "rsrp_dbm", "throughput_mbps"]
    ul = uplink_fields(uplink_columns(uplink_arrays(np.array([23.0004, 1.5]), np.array([np.nan, 2.2226]),
                                                    np.array([1.0, 2.0]), {k: v[:2] for k, v in link.items()})))
    assert ul[0]["ul_tx_power_dbm"] == 23.0 and ul[0]["ul_sinr_db"] is None and ul[1]["ul_sinr_db"] == 2.223
    assert ul[0]["ul_tbler"] == 0.1235 and ul[1]["ul_mcs"] == -1


@pytest.mark.parametrize("digits", [2, 3, 4, 6])
def test_rounding_in_bulk_is_pythons_round_bit_for_bit(digits):
    """``rounded`` (rint on the scaled values, Python's round near ties) gives what ``round(float(v),
    digits)`` gives: on noise, on values a digit finer (ties in decimal, not in binary), on the
    classic ties and signed zeros, and leaves non-finite values."""
    rng = np.random.default_rng(digits)
    values = np.concatenate([rng.normal(0, 100, 20000), np.round(rng.uniform(-300, 300, 20000), digits + 1),
                             rng.normal(0, 1e9, 100), [2.675, 1.005, 0.125, -0.125, 0.5, -0.5, 2.5, -1e-300, -0.0,
                                                       1e300, np.inf, -np.inf]])
    got = rounded(values, digits)
    want = [round(float(v), digits) if math.isfinite(v) else float(v) for v in values]
    assert got == want
    assert [math.copysign(1, g) for g in got] == [math.copysign(1, w) for w in want]  # (-0.0 stays)
    assert np.isnan(rounded(np.array([np.nan]), digits)[0]) and rounded(np.ones((2, 2)), 1) == [[1.0, 1.0]] * 2


def test_a_slot_broadcast_sinr_gives_what_its_copy_gives():
    """Every slot the same SINRs (a stride-0 view, as a flat channel's): converted once and
    repeated on the device, the same results as the materialised copy's."""
    rng = np.random.default_rng(2)
    settings = LinkSettings(num_prb=24, harq_processes=4, subbands=2)
    one = 8.0 + rng.normal(0, 4, size=(1, 6, 2))
    one[0, 5] = np.nan  # (a UE without a cell)
    serving = np.array([0, 0, 1, 1, 1, -1])
    view = np.broadcast_to(one, (16, 6, 2))
    assert view.strides[0] == 0
    a = LinkLevel(settings, n_cell=2, seed=4).run(view, serving)
    b = LinkLevel(settings, n_cell=2, seed=4).run(np.ascontiguousarray(view), serving)
    for field in ("decoded_bits", "prbs", "acks", "nacks", "mcs", "cells_active", "delivered_bits"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert a.prbs[:5].sum() > 0 and a.prbs[5] == 0


def test_cuda_graphs_are_on_by_default_only_for_a_compiled_link_level_on_cuda():
    import torch

    base = LinkSettings(num_prb=24, compile=True)
    # (on by default on CUDA: the OLLA's state that failed on the H200 now copied out of each replay)
    assert cuda_graphs_on(base, torch.device("cuda")) and cuda_graphs_on(base, torch.device("cuda", 1))
    assert not cuda_graphs_on(base, torch.device("cpu")) and not cuda_graphs_on(base, "cpu")
    assert cuda_graphs_on(dataclasses.replace(base, cuda_graphs=True), torch.device("cuda"))
    assert not cuda_graphs_on(dataclasses.replace(base, compile=False), torch.device("cuda"))
    assert not cuda_graphs_on(dataclasses.replace(base, cuda_graphs=False), torch.device("cuda"))
    assert cuda_graphs_on(dataclasses.replace(base, cuda_graphs=True), torch.device("cpu"))
    with pytest.raises(ValueError, match="cuda_graphs: .*needs compile = true"):
        LinkSettings(num_prb=24, cuda_graphs=True)
    with pytest.raises(ValueError, match="cuda_graphs: expected true, false or none"):
        LinkSettings(num_prb=24, compile=True, cuda_graphs="yes")  # type: ignore[arg-type]
    assert LinkLevel(LinkSettings(num_prb=24), n_cell=1).cuda_graphs is False


def _graph_mode_case(seed: int, d: int) -> tuple:
    """One cell of 3 UEs, one group of ``d`` slots on 2 subbands: the SINRs, the serving cells, the
    settings, eager's results and a compiled link level in CUDA-graph mode (both seeded 11)."""
    sinr = 14.0 + np.random.default_rng(seed).normal(0.0, 3.0, size=(d, 3, 2))
    serving = np.zeros(3, dtype=int)
    settings = LinkSettings(num_prb=24, harq_processes=d, subbands=2)
    eager = LinkLevel(settings, n_cell=1, seed=11).run(sinr, serving)
    return sinr, serving, settings, eager, LinkLevel(dataclasses.replace(settings, compile=True, cuda_graphs=True),
                                                     n_cell=1, seed=11)


def test_the_cuda_graph_mode_on_the_cpu_decides_as_eager():
    """``cuda_graphs = true`` on the CPU: compiled in ``reduce-overhead`` mode (torch captures
    no graph there), its outputs copied out; the first call's MCS, PRBs, effective SINR and TBLER
    are eager's, a second call's tallies stand apart from the first's, and the OLLA's state is
    copied out of each replay."""
    import torch

    d = 4
    sinr, serving, settings, eager, graphed = _graph_mode_case(6, d)
    assert graphed.cuda_graphs and graphed._group == graphed._group_graphed
    compiled, left = graphed._compiled, []

    def replay(*args):  # (the OLLA's state as each replay leaves it: on a GPU, the graph's memory)
        out = compiled(*args)
        left.append((graphed.olla, graphed.olla._offset, graphed.olla._sinr_eff_db_last))
        return out

    graphed._compiled = replay
    first = graphed.run(sinr, serving)
    assert_decides_as(first, eager)
    kept = first.decoded_bits.copy()
    second = graphed.run(np.concatenate([sinr, sinr]), serving)
    np.testing.assert_array_equal(first.decoded_bits, kept)
    assert (second.acks + second.nacks).sum() == 2 * d  # one UE of the cell's a slot, both groups
    # Copied out after each replay (the next replay overwrites the graph's memory: the H200's failure).
    olla, offset, sinr_last = left[-1]
    assert len(left) == 3 and olla is graphed.olla and (offset != 0).any()
    for state, replayed in ((olla._offset, offset), (olla._sinr_eff_db_last, sinr_last)):
        assert torch.equal(state, replayed) and state.data_ptr() != replayed.data_ptr()


def test_a_replay_torch_refuses_goes_on_compiled_without_graphs(capsys):
    """Where torch refuses a CUDA graph's replay (as it did on the H200: "accessing tensor output of
    CUDAGraphs that has been overwritten", raised before the graph runs), the link level says so
    and goes on compiled without graphs: the same decisions as eager; another error is not hidden."""
    sinr, serving, settings, eager, graphed = _graph_mode_case(9, 4)

    def refused(*args):
        raise RuntimeError("Error: accessing tensor output of CUDAGraphs that has been overwritten by a subsequent run")

    graphed._compiled = refused
    assert_decides_as(graphed.run(sinr, serving), eager)
    assert not graphed.cuda_graphs and graphed._group is graphed._compiled
    assert "a CUDA graph's replay failed (Error: accessing tensor output of CUDAGraphs" in capsys.readouterr().err
    other = LinkLevel(dataclasses.replace(settings, compile=True, cuda_graphs=True), n_cell=1, seed=11)
    other._compiled = lambda *args: (_ for _ in ()).throw(RuntimeError("shape mismatch"))
    with pytest.raises(RuntimeError, match="shape mismatch"):
        other.run(sinr, serving)


def test_with_cuda_graphs_a_chunk_of_groups_is_a_loop_that_decides_as_the_groups_one_a_call():
    """``cuda_graphs`` and ``groups_per_call`` together (on the CPU: graph mode without graphs): a
    chunk is the loop, compiled without a graph (one cannot hold the loop's host-side index), the
    single groups the graph mode's calls; both draw from the device's generator as seeded, so two
    groups in a chunk decide as two graphed calls, bit for bit."""
    rng = np.random.default_rng(8)
    d, sub = 4, 2
    sinr = 14.0 + rng.normal(0.0, 3.0, size=(2 * d, 5, sub))
    serving = np.array([0, 0, 1, 1, -1])
    settings = LinkSettings(num_prb=24, harq_processes=d, subbands=sub, compile=True, cuda_graphs=True)
    runs = []
    for groups in (1, 2):  # (each made just before its run: the generator seeded as the link level's)
        level = LinkLevel(dataclasses.replace(settings, groups_per_call=groups), n_cell=2, seed=12)
        runs.append(level.run(sinr, serving))
        assert level.cuda_graphs and (level._many is None) == (groups == 1)
    for field in ("decoded_bits", "prbs", "acks", "nacks", "mcs", "cells_active", "delivered_bits"):
        np.testing.assert_array_equal(getattr(runs[1], field), getattr(runs[0], field), err_msg=field)
    assert runs[0].prbs.sum() > 0


def test_a_position_that_is_not_three_numbers_is_named():
    table = UeTable()
    table.place([{"UE_Id": "car1", "UE_type": "car", "position": {"x": 1.0, "y": 2.0, "z": 0.0}}], 1.5)
    with pytest.raises(ValueError, match=r"UE 'car2' is at \{'x': 3.0, 'y': None, 'z': 0.0\}: expected finite numbers"):
        table.place([{"UE_Id": "car1", "UE_type": "car", "position": {"x": 1.0, "y": 2.0, "z": 0.0}},
                     {"UE_Id": "car2", "UE_type": "car", "position": {"x": 3.0, "y": None, "z": 0.0}}], 1.5)
    np.testing.assert_array_equal(table.position[table.column("car1")], [1.0, 2.0, 0.0])
    with pytest.raises(ValueError, match=r"UE 'car3' is at .*'z': 'up'.*: expected finite numbers"):
        table.place([{"UE_Id": "car1", "UE_type": "car", "position": {"x": 1.0, "y": 2.0, "z": 0.0}},
                     {"UE_Id": "car3", "UE_type": "car", "position": {"x": 3.0, "y": 1.0, "z": "up"}}], 1.5)


def test_rounded_array_is_pythons_round_on_ties_large_and_non_finite_values():
    """:func:`rounded_array` against ``round(float(x), d)`` element by element: exact decimal
    ties (k + 0.5 at the last digit, which Python rounds to even on the binary value), values
    near them, large ones (where ``x·10^d`` itself errs), signed zeros and non-finite values."""
    rng = np.random.default_rng(11)
    for digits in (2, 3, 4, 6):
        ties = (np.arange(-3000, 3000) + 0.5) / 10**digits
        values = np.concatenate([ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf),
                                 rng.normal(-90, 30, 5000), rng.uniform(-1e12, 1e12, 500),
                                 [0.0, -0.0, -1e-9, 2.675, 1.005, 0.125, 1e300, np.inf, -np.inf, np.nan]])
        got = rounded_array(values, digits)
        want = np.array([round(float(x), digits) if math.isfinite(x) else x for x in values])
        np.testing.assert_array_equal(got, want, err_msg=f"{digits} digits")
        assert (np.signbit(got) == np.signbit(want)).all()  # (-0.0 stays -0.0, as Python's)
