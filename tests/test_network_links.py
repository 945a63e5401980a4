"""One link level for the downlink and the uplink (``LinkLevel.run_links``): each group of slots
is one call for both links, and each link decides as a link level of its own would, its loops
and histories its own; a link with nothing queued in a group sits it out."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from caviar_plugins.network.traffic import Backlog
from caviar_plugins.radio import link_chunks, sionna_sys_adapter, slot_results
from caviar_plugins.radio.link_level import LinkLevel, LinkSettings
from caviar_plugins.radio.slot_results import RESULTS

D, SLOTS, N_UE, N_CELL = 4, 24, 12, 2


def _calls(rng: np.random.Generator, subbands: int, serving: np.ndarray) -> list[tuple]:
    """Two calls' SINRs of both links, far from the BLER waterfall (-20 or 40 dB, a UE's every
    slot and subband alike): every HARQ outcome is certain, so that two random streams cannot
    tell the links apart; and the uplink's backlogs: a little queued at the start for one UE at
    40 dB (served in the first group), nothing in the next two (they sit out), more for everyone at slot 12."""
    calls = []
    for _ in range(2):
        dl, ul = (np.broadcast_to(rng.choice([-20.0, 40.0], (1, N_UE, 1)), (SLOTS, N_UE, subbands)) for _ in range(2))
        arrivals = np.zeros((SLOTS, N_UE))
        arrivals[12] = 2e5
        first = np.zeros(N_UE)
        first[np.flatnonzero((ul[0, :, 0] > 0) & (serving >= 0))[0]] = 500.0
        calls.append((dl, ul, Backlog(first, arrivals)))
    return calls


def _same(got, want, compiled: bool, msg: str) -> None:
    """Equal, bit for bit; compiled, the floats to float32's precision (its EESM's sums fused)."""
    got, want = np.asarray(got), np.asarray(want)
    if compiled and np.issubdtype(want.dtype, np.floating):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-3, err_msg=msg)
    else:
        np.testing.assert_array_equal(got, want, err_msg=msg)


@pytest.mark.parametrize(("subbands", "scheduler", "compiled"), [
    (1, "proportional-fair", False), (4, "proportional-fair", False), (4, "round-robin", False),
    (4, "max-rate", False), (4, "proportional-fair", True)])
def test_downlink_and_uplink_together_decide_as_two_link_levels(subbands, scheduler, compiled):
    rng = np.random.default_rng(12)
    dl_settings = LinkSettings(num_prb=24, harq_processes=D, subbands=subbands, scheduler=scheduler, device="cpu",
                               bler_target=0.005)  # (the MCS whose BLER is 0 at 40 dB)
    ul_settings = dataclasses.replace(dl_settings, direction="uplink", mcs_table=2)
    serving = rng.integers(-1, N_CELL, N_UE)
    together = LinkLevel([dataclasses.replace(dl_settings, compile=compiled),
                          dataclasses.replace(ul_settings, compile=compiled)], N_CELL, seed=3)
    dl, ul = LinkLevel(dl_settings, N_CELL, seed=3), LinkLevel(ul_settings, N_CELL, seed=4)
    scheduled = 0
    for dl_sinr, ul_sinr, backlog in _calls(rng, subbands, serving):
        both = together.run_links([dl_sinr, ul_sinr], serving, SLOTS, [None, backlog])
        alone = [dl.run(dl_sinr, serving), ul.run(ul_sinr, serving, backlog=backlog)]
        for got, want, name in zip(both, alone, ("downlink", "uplink"), strict=True):
            served = want.scheduled_slots > 0
            # (the premise: every outcome certain, TBLER 0 or 1)
            assert np.isin(want.tbler[served], (0.0, 1.0)).all(), (name, want.tbler)
            for field in RESULTS:
                _same(getattr(got, field), getattr(want, field), compiled, f"{name}: {field}")
            scheduled += int(served.sum())
        # Each link's loops and histories are its own link level's (the uplink's, sat out or not).
        kept = together.state()
        for i, one in enumerate((dl, ul)):
            alone_state = one.state()
            for block in ("olla", "pf"):
                for name, value in alone_state[block].items():
                    width = value.shape[-1]  # (a compiled link level has room for more UEs)
                    _same(kept[block][name][i][..., :width], value[0], compiled, f"link {i}: {block} {name}")
            for name in ("harq", "rate_last"):
                width = alone_state[name].shape[-1]
                _same(kept[name][i][..., :width], alone_state[name][0], compiled, f"link {i}: {name}")
        # The uplink sat out its second and third groups: nothing scheduled there.
        active = both[1].cells_active.any(axis=1)
        assert active[:D].any() and not active[D:3 * D].any() and active[3 * D:].all()
    assert scheduled > 0


def test_links_that_differ_beyond_direction_and_table_are_refused():
    dl = LinkSettings(num_prb=24, harq_processes=D)
    with pytest.raises(ValueError, match="share every setting but their direction and MCS table"):
        LinkLevel([dl, dataclasses.replace(dl, direction="uplink", harq_processes=2)], N_CELL)
    together = LinkLevel([dl, dataclasses.replace(dl, direction="uplink")], N_CELL)
    with pytest.raises(ValueError, match="runs 2 links together: call run_links"):
        together.run(np.zeros((D, 3)), np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match=r"the SINRs of 2 link\(s\) \(downlink, uplink\), got 1"):
        together.run_links([np.zeros((D, 3))], np.zeros(3, dtype=int), D)
    with pytest.raises(ValueError, match="a link level's state of 1 link"):
        together.restore(LinkLevel(dl, N_CELL).state())


def test_several_groups_a_compiled_call_decide_as_one_a_call(monkeypatch):
    """``groups_per_call``: with full buffers, chunks of groups of slots run as one compiled call
    (those left over one a call), a loop compiled once (``scan``), and every result and loop state
    is one-a-call's, bit for bit (the random stream included; chunks of every slot tallied in their
    compiled programs, carried from chunk to chunk); with queues, one a call."""
    rng = np.random.default_rng(14)
    dl = LinkSettings(num_prb=24, harq_processes=D, subbands=4, compile=True, device="cpu")
    links = [dl, dataclasses.replace(dl, direction="uplink")]
    serving = rng.integers(-1, N_CELL, N_UE)
    one, many = (LinkLevel([dataclasses.replace(s, groups_per_call=g) for s in links], N_CELL, seed=3) for g in (1, 2))
    chunks: list = []
    inner = many._groups
    many._groups = lambda *a: chunks.append(len(a[0])) or inner(*a)
    loops: list = []
    scan = sionna_sys_adapter.torch_scan
    monkeypatch.setattr(sionna_sys_adapter, "torch_scan", lambda: loops.append(1) or scan())
    tallies: list = []  # (the calls tallied after their groups, on the host's side)
    eager = slot_results.per_ue
    monkeypatch.setattr(slot_results, "per_ue", lambda *a: tallies.append(a[1].shape[1]) or eager(*a))
    for groups in (2, 4, 5):  # (2, 4: chunks of every slot, tallied in them; 5: two chunks of 2, then one group alone)
        sinrs = [14.0 + rng.normal(0.0, 6.0, (groups * D, N_UE, 4)) for _ in links]
        for got, want in zip(many.run_links(sinrs, serving, groups * D), one.run_links(sinrs, serving, groups * D),
                             strict=True):
            for name in RESULTS:
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert chunks == [2, 2, 2, 2, 2] and len(loops) == len(chunks)  # (each chunk a loop)
    assert tallies == [2 * D, 4 * D, 5 * D, 5 * D]  # (one-a-call's each time; many's where a group ran alone)
    for block in ("olla", "pf"):
        for name, value in one.state()[block].items():
            np.testing.assert_array_equal(many.state()[block][name], value, err_msg=f"{block} {name}")
    backlog = Backlog(np.full(N_UE, 1e4), np.zeros((6 * D, N_UE)))
    many.run_links([np.full((6 * D, N_UE, 4), 14.0)] * 2, serving, 6 * D, [backlog, None])
    assert chunks == [2, 2, 2, 2, 2]  # (queues: one group a call)
    with pytest.raises(ValueError, match="groups_per_call: runs groups of slots as one compiled call"):
        LinkSettings(num_prb=24, groups_per_call=2)
    # Past torch's limit of compiled entries (the chunk one graph: no eager fallback of its own), a new
    # link level's chunks run their groups one a call: they go on, as one a call would.
    import torch

    late = LinkLevel([dataclasses.replace(s, groups_per_call=2) for s in links], N_CELL, seed=3)
    sinrs = [14.0 + rng.normal(0.0, 6.0, (2 * D, N_UE, 4)) for _ in links]
    fresh = LinkLevel([dataclasses.replace(s, groups_per_call=1) for s in links], N_CELL, seed=3)
    with torch._dynamo.config.patch(recompile_limit=1):
        runs = late.run_links(sinrs, serving, 2 * D), fresh.run_links(sinrs, serving, 2 * D)
    for got, want in zip(*runs, strict=True):
        for name in RESULTS:
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=f"past the limit: {name}")
    assert chunks[-1] == 2 and late.state()["harq"].shape == fresh.state()["harq"].shape


@pytest.mark.parametrize(("subbands", "scheduler"), [(4, "proportional-fair"), (1, "round-robin")])
def test_a_chunk_as_a_loop_and_written_out_give_the_same_slots_and_state(subbands, scheduler):
    """The two ways of a chunk of groups (:mod:`caviar_plugins.radio.link_chunks`): the loop and the
    groups one after the other (where torch's limit of compiled entries refuses the loop), traced
    by dynamo (its random draws from torch's default generator, put back between them): the same
    slots, tallies and loop state, bit for bit, over three groups; subbands or one (whose SINR
    leaves the PHY abstraction as it came), the PF scheduler or round robin (the PF block idle)."""
    import torch

    rng = np.random.default_rng(3)
    dl = LinkSettings(num_prb=24, harq_processes=D, subbands=subbands, scheduler=scheduler)
    links = [dl, dataclasses.replace(dl, direction="uplink")]
    serving = rng.integers(-1, N_CELL, N_UE)
    level = LinkLevel(links, N_CELL, seed=5)
    level.run_links([14.0 + rng.normal(0.0, 6.0, (D, N_UE, subbands)) for _ in links], serving, D)  # (blocks built)
    lin = torch.stack([level._linear_in(14.0 + rng.normal(0.0, 6.0, (3 * D, N_UE, subbands)), serving, 3 * D)
                       .view(3, D, subbands, -1) for _ in links], dim=1)  # [G, L, D, S, cap]
    member = torch.zeros((2, N_CELL, level.capacity), dtype=torch.bool)
    member[:, serving[serving >= 0], np.flatnonzero(serving >= 0)] = True
    args = (lin, member, torch.arange(0, 3 * D, D), level.harq, level.rate_last, torch.ones(2, dtype=torch.bool),
            level._no_tallies)
    before = {k: sionna_sys_adapter.block_state(b) for k, b in (("olla", level.olla), ("pf", level.pf))}
    pf_schedules = scheduler == "proportional-fair"
    start = torch.default_generator.get_state()
    outs, states = [], []
    for way in (lambda *a: link_chunks.unrolled(level._group_eager, *a),
                lambda *a: link_chunks.scanned(level._group_eager, (level.olla, level.pf, pf_schedules), *a)):
        torch.default_generator.set_state(start)
        for name, block in (("olla", level.olla), ("pf", level.pf)):
            sionna_sys_adapter.set_block_state(block, before[name])
        outs.append(torch.compile(way, backend="eager", fullgraph=True, dynamic=False)(*args))
        states.append({k: sionna_sys_adapter.block_state(b) for k, b in (("olla", level.olla), ("pf", level.pf))})
    assert len(outs[0]) == len(outs[1]) == 10
    for k, (a, b) in enumerate(zip(*outs, strict=True)):
        assert a.shape == b.shape and torch.equal(a.nan_to_num(-7.0), b.nan_to_num(-7.0)), k
    assert outs[0][1].shape == (2, 3 * D, level.capacity) and (outs[0][6] > 0).any()  # (slots in order, bits decoded)
    for name in ("olla", "pf"):
        for key, value in states[0][name].items():
            assert torch.equal(value, states[1][name][key]), (name, key)
            # (the groups ran: the loops moved; the PF block's only where it schedules)
            assert torch.equal(value, before[name][key]) is (name == "pf" and not pf_schedules), (name, key)
