"""A chunk of groups of slots as one compiled call of a link level (``groups_per_call``), two ways:

- :func:`scanned`: a loop over the groups (``torch._higher_order_ops.scan``) that torch compiles
  once, its body one group, whatever the chunk's length: the host enters one compiled program a
  chunk and the compile takes as long for 25 groups as for 2 (written out one after the other,
  25 groups a call compiled in about 240 s on a 2-core machine). Sionna's OLLA and PF blocks run
  in the body on state the loop carries (:func:`~caviar_plugins.radio.sionna_sys_adapter.loops_on`:
  the body may change no object from outside it), set on the blocks after the loop.
- :func:`unrolled`: the groups one after the other, each a call of ``group`` (a link level's
  compiled group: where torch's limit of compiled entries refuses the loop), and the loop's
  reference in the tests. (A chunk is no CUDA graph: the loop's index lives on the host, which a
  captured graph does not run; with ``cuda_graphs`` the one-group calls are graphs.)

Both give what :meth:`~caviar_plugins.radio.link_level.LinkLevel._group_eager` gives group after
group, bit for bit, the random numbers included (the loop draws each group's seed in its turn, as
the groups do one a call, or written out in one program, a chunk's seeds at once: the same
numbers; tests/test_network_links.py).
"""

from __future__ import annotations

from typing import Any

from caviar_plugins.radio import sionna_sys_adapter as adapter
from caviar_plugins.radio.slot_results import carried, per_ue


def scanned(group: Any, loops: tuple, lin_g, member_t, firsts_g, harq_last, rate_last, went, tallies):
    """G groups of slots in a row as one loop of ``group`` (a link level's ``_group_eager``) with the
    link level's OLLA and PF blocks and whether the PF block schedules, ``loops`` (``lin_g`` [G, L, D,
    S, cap], ``firsts_g`` [G]; the rest as ``group`` takes them): their outputs as one group of G·D
    slots would give them, [L, G·D, ...], each UE's ``tallies`` [L, 8, cap] of the slots before them
    carried over them (:func:`~caviar_plugins.radio.slot_results.carried`), then the state the last
    one left."""
    olla, pf, pf_schedules = loops

    def step(carry, x):
        harq, rate, *tensors = carry
        on_state = adapter.loops_on(olla, pf, tuple(tensors), pf_schedules)
        prbs, harq_g, tbler, mcs, sinr_eff, cells, bits, harq, rate = group(x[0], member_t, x[1], harq, rate, went,
                                                                            on_state)
        # (a wideband SINR leaves the PHY abstraction as it came: a view of the loop's input, which
        # a loop's output may not be)
        out = (prbs, harq_g, tbler, mcs, sinr_eff.clone(), cells, bits)
        return (harq, rate, *adapter.loop_tensors(*on_state)), out

    carry, ys = adapter.torch_scan()(step, (harq_last, rate_last, *adapter.loop_tensors(olla, pf)), (lin_g, firsts_g))
    adapter.set_loop_tensors(olla, pf, tuple(carry[2:]))
    # (each output [G, L, D, ...] -> [L, G·D, ...]: the groups' slots in order)
    fields = tuple(y.transpose(0, 1).reshape(y.shape[1], -1, *y.shape[3:]) for y in ys)
    return _tallied(fields, tallies) + tuple(carry[:2])


def unrolled(group: Any, lin_g, member_t, firsts_g, harq_last, rate_last, went, tallies):
    """:func:`scanned`'s results, the groups one after the other (with the link level's own blocks)."""
    import torch

    outs = []
    for g in range(lin_g.shape[0]):
        *out, harq_last, rate_last = group(lin_g[g], member_t, firsts_g[g], harq_last, rate_last, went)
        outs.append(out)
    fields = tuple(torch.cat(x, dim=1) for x in zip(*outs, strict=True))
    return _tallied(fields, tallies) + (harq_last, rate_last)


def _tallied(fields: tuple, tallies: Any) -> tuple:
    """(PRBs, HARQ, TBLER, MCS, effective SINR, cells, bits, the tallies carried over them)."""
    import torch

    prbs, harq, tbler, mcs, sinr_eff, _, bits = fields
    return (*fields, carried(torch, tallies, per_ue(torch, prbs, harq, tbler, mcs, sinr_eff, bits)))
