"""The link level, abstracted: Sionna SYS on the twin's channels, slot by slot (the
radio network's cells and sionna-link's `link_model = "sys"` both use it).

Per slot, for every cell at once (one batched call per block):

1. **Scheduling.** Sionna's proportional-fair scheduler (:class:`sionna.sys.PFSchedulerSUMIMO`)
   gives each PRB of a cell to one of the cell's UEs, by achievable rate
   (``log2(1 + SINR)`` per PRB) over the UE's discounted past rate in that cell.
   ``round-robin`` and ``max-rate`` are there to compare with.
2. **Link adaptation.** Sionna's outer-loop link adaptation
   (:class:`sionna.sys.OuterLoopLinkAdaptation`) picks each UE's MCS: the highest whose
   transport BLER at the reported SINR (ideal CSI: the slot's) minus an offset stays
   below the target; the offset follows the HARQ feedback (down on ACK, up on NACK).
3. **PHY abstraction.** :class:`sionna.sys.PHYAbstraction` maps (MCS, effective SINR,
   allocated resource elements) to the BLER of Sionna's shipped NR tables, draws the
   HARQ outcome and counts the decoded bits.

A co-simulation step (say 10 ms) runs its slots (say 0.5 ms each) in a loop of such
calls, on per-slot SINRs the caller provides: ``[n_slots, n_ue]`` for a wideband
channel, or ``[n_slots, n_ue, subbands]`` for a frequency-selective one. With subbands
the scheduler gives each subband (a group of adjacent PRBs) to one UE, the UE reports
its allocation's SINR averaged in dB (the CQI; the outer loop corrects its bias) and
the PHY abstraction maps the SINRs of its allocated PRBs to one effective SINR with
Sionna's EESM (:class:`sionna.sys.EESM`). The Shannon link model (``shannon``) shares
each cell's time equally among its UEs at ``Σ_subbands B_k·log2(1 + SINR_k)`` instead.

UEs come and go and hand over: each UE has a column in the blocks' state, kept
across steps; a UE that changes cell starts with a fresh proportional-fair history
there.

One link level may run several links of the same cells and UEs at once (the network's downlink
and uplink, :meth:`LinkLevel.run_links`): every block then has a leading link axis, each link keeps
its own loops, histories and MCS tables (PDSCH or PUSCH), and a group of slots is one call for
all of them (on a GPU, one compiled program; on any machine, half the host's work of two link
levels). A link with nothing queued in a group sits it out: its loops and histories stay as
they were.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from typing import Any, Iterator, Sequence

import numpy as np

from caviar_plugins.radio import link_chunks
from caviar_plugins.radio import sionna_sys_adapter as adapter
from caviar_plugins.radio.link_queue import CallQueue as _Queue
from caviar_plugins.radio.link_settings import DATA_SYMBOLS_PER_SLOT, LinkSettings, cuda_graphs_on
from caviar_plugins.radio.shannon_slots import shannon_slots
from caviar_plugins.radio.slot_results import SlotResults, no_tallies, tallied
from caviar_plugins.torch_device import default_generator, resolve, to_numpy, to_torch

COMPILED_CAPACITY = 128
"""UE columns a compiled link level starts with (growing past them compiles again)."""
CHECKED_CALLS = 8
"""Calls of a compiled group of slots that dynamo checks in full (every guard of its compiled
entries) at a UE capacity, after which the link level's further calls there check only the guards
that tell the entries apart (:meth:`LinkLevel._guards`)."""


@dataclasses.dataclass
class _CallPlan:
    """A call's groups of slots, as :meth:`LinkLevel._groups_at` runs them."""

    d: int  # slots a group
    queues: list[_Queue]
    finite: bool  # (a link's queue is not a full buffer)
    member: Any  # [L, C, cap]: whom each link's cell may schedule
    went: Any  # [L] True: every link (full buffers)
    blocks: tuple  # each group's SINRs, [L, D, S, cap]
    firsts: tuple  # each group's first slot (0-d tensors)
    many: int  # groups a call in chunks (groups_per_call; 1: none)
    in_many: int  # groups run in chunks (the first ones)
    chunks: tuple  # each chunk's SINRs, [many, L, D, S, cap]
    chunk_firsts: tuple  # each chunk's groups' first slots, [many]
    tallies: Any  # [L, 8, cap]: each UE's tallies of the chunks run so far (slot_results.per_ue, carried)


def joint_links(settings: LinkSettings | Sequence[LinkSettings]) -> tuple[LinkSettings, ...]:
    """The links one :class:`LinkLevel` runs: ``settings``, or each of a sequence of them,
    which must agree on everything but their direction and MCS table."""
    links = (settings,) if isinstance(settings, LinkSettings) else tuple(settings)
    if not links:
        raise ValueError("a link level needs the settings of at least one link")
    first = links[0]
    for k, other in enumerate(links[1:], 1):
        if dataclasses.replace(other, direction=first.direction, mcs_table=first.mcs_table) != first:
            raise ValueError(f"links run together share every setting but their direction and MCS table: "
                             f"link {k} ({other}) differs from link 0 ({first})")
    return links


class LinkLevel:
    """Scheduling, link adaptation and PHY abstraction for ``n_cell`` cells, on one link or on
    several at once (``settings`` a sequence: :meth:`run_links`)."""

    def __init__(self, settings: LinkSettings | Sequence[LinkSettings], n_cell: int, seed: int = 0,
                 capacity: int = 8):
        self.links = joint_links(settings)
        self.s = self.links[0]
        settings = self.s
        self.n_cell = n_cell
        self.capacity = 0
        self.seed = seed
        self._sys: Any = None
        self.olla: Any = None
        self.pf: Any = None
        self.harq: Any = None
        self.rate_last: Any = None
        self._no_tallies: Any = None
        if settings.link_model == "sys":
            import sionna.phy
            import sionna.sys

            self._sys = sionna.sys
            self._torch = __import__("torch")
            self.device = resolve(settings.device)
            # The link level's own random stream (no global seed set): the HARQ outcomes the PHY
            # abstraction draws, eager from this generator, compiled from the device's default
            # generator with this stream's state swapped in for the call's groups (_own_stream).
            self._generator = adapter.own_generator(self.device, seed)
            self._compiled_rng = adapter.own_generator(self.device, seed).get_state()
            self.phy = adapter.phy_abstraction(self.device, self._generator)
            self.eesm = sionna.sys.EESM(device=str(self.device))
            self._prb_weights = to_torch(settings.subband_prbs, self.device, self._torch.float32)
            # each PRB's subband, [num_prb] (the EESM's input by one gather, of a fixed shape)
            self._prb_subband = to_torch(np.repeat(np.arange(settings.subbands), settings.subband_prbs),
                                         self.device, self._torch.int64)
            self._all_links = self._torch.ones(len(self.links), dtype=self._torch.bool, device=self.device)
        self._group = self._group_eager
        self._compiled: Any = None
        self._many: Any = None  # (several groups a call: settings.groups_per_call, full buffers)
        self._checked = 0  # (compiled calls at this capacity under every guard: _guards)
        self.cuda_graphs = False
        if settings.compile and settings.link_model == "sys":
            # The whole group of slots (scheduler, CSI, loops, PHY abstraction) is one
            # compiled program: on a GPU a handful of kernels a group, not hundreds, and with
            # CUDA graphs one launch.
            self.cuda_graphs = cuda_graphs_on(settings, self.device)
            self._compiled = self._torch.compile(self._group_eager, dynamic=False,
                                                 mode="reduce-overhead" if self.cuda_graphs else None)
            self._group = self._group_graphed if self.cuda_graphs else self._compiled
            if settings.groups_per_call > 1:  # (one graph: a loop's index is read on the host in it; no
                # CUDA graph, which cannot hold a host loop: with cuda_graphs, the one-group calls are)
                self._many = self._torch.compile(self._groups_eager, dynamic=False, fullgraph=True)
            if self.cuda_graphs:  # (a captured graph replays the device generator it captured: seeded here)
                default_generator(self.device).set_state(self._compiled_rng)
            # Each link level, UE capacity and direction compiles its own entries (without chunks, two
            # each: before and after Sionna builds its blocks); past torch's limit (8) they run eager.
            adapter.allow_recompiles(self._torch, 64)
            capacity = max(capacity, COMPILED_CAPACITY)  # each growth compiles again
            print(f"link level: torch.compile for {capacity} UEs at the first slots (about 20 s, once)",
                  file=sys.stderr, flush=True)
        self._grow(capacity)

    def _grow(self, capacity: int) -> None:
        """Room for ``capacity`` UEs, keeping the state of the first ``self.capacity``.
        State, per link l and HARQ process d: OLLA offset and last SINR [L, D, cap], PF history
        [L, D, cell, cap], last HARQ outcome [L, D, cap] and achieved rate [L, D, cell, cap]."""
        old = self.capacity
        self.capacity = capacity
        self._checked = 0  # (new blocks, new shapes: checked in full again)
        if self._sys is None:
            return
        torch = self._torch
        n, d, c = len(self.links), self.s.harq_processes, self.n_cell
        olla = self._sys.OuterLoopLinkAdaptation(self.phy, num_ut=capacity, bler_target=self.s.bler_target,
                                                 batch_size=[n, d], device=str(self.device))
        # The PF metric is the same on every PRB of a subband, so Sionna's scheduler decides
        # on one resource per subband, standing for its PRBs.
        pf = self._sys.PFSchedulerSUMIMO(capacity, self.s.subbands, 1, batch_size=[n, d, c], device=str(self.device))
        harq = torch.full((n, d, capacity), -1, dtype=torch.int32, device=self.device)
        rate_last = torch.zeros(n, d, c, capacity, device=self.device)
        if old:
            adapter.grow_link_adaptation(olla, self.olla, old)
            adapter.grow_scheduler(pf, self.pf, old)
            harq[..., :old], rate_last[..., :old] = self.harq, self.rate_last
        self.olla, self.pf, self.harq, self.rate_last = olla, pf, harq, rate_last
        if self._many is not None:  # (built before a loop's body calls them: chunks of groups)
            adapter.built(self.phy, self.eesm, olla, pf)
        self._no_tallies = no_tallies(torch, n, capacity, self.device)  # (where a call's chunks start)
        # Each link's MCS table and category (PDSCH or PUSCH): a number where the links share it,
        # else a tensor [L, D, cap] (Sionna's blocks take one per UE).
        self._mcs_table, self._mcs_category = (self._per_link([s.mcs_table for s in self.links], capacity),
                                               self._per_link([s.mcs_category for s in self.links], capacity))

    def _per_link(self, values: list[int], capacity: int) -> Any:
        if len(set(values)) == 1:
            return values[0]
        torch, shape = self._torch, (len(values), self.s.harq_processes, capacity)
        return torch.tensor(values, dtype=torch.int32, device=self.device)[:, None, None].expand(shape).contiguous()

    def state(self) -> dict[str, Any]:
        """What changes from slot to slot, for a checkpoint: the capacity, every tensor the OLLA loops and the PF
        scheduler keep, the HARQ outcomes, the achieved rates and the position of Sionna's random stream (the PHY
        abstraction's ACK draws)."""
        if self._sys is None:
            return {"capacity": self.capacity, "links": len(self.links)}
        return {"capacity": self.capacity, "links": len(self.links),
                "olla": adapter.block_state(self.olla), "pf": adapter.block_state(self.pf),
                "harq": self.harq.clone(), "rate_last": self.rate_last.clone(),
                "rng": self._generator.get_state(), "compiled_rng": self._compiled_rng.clone()}

    def restore(self, state: dict[str, Any]) -> None:
        """Puts back :meth:`state` into a link level built with the same settings."""
        if state.get("links") != len(self.links):
            raise ValueError(f"a link level's state of {state.get('links', 'unknown')} link(s), put back into one of "
                             f"{len(self.links)} (a checkpoint of other settings, or of a version before 2026-11-29)")
        if state["capacity"] > self.capacity:
            self._grow(state["capacity"])
        if self._sys is None:
            return
        for obj, saved in ((self.olla, state["olla"]), (self.pf, state["pf"])):
            adapter.set_block_state(obj, saved)
        self.harq, self.rate_last = state["harq"].clone(), state["rate_last"].clone()
        self._generator.set_state(state["rng"])
        self._compiled_rng = state["compiled_rng"].clone()
        self._checked = 0  # (tensors put back: checked in full again)

    def table_bler(self, mcs: int, sinr_db: float, cb_size: int) -> float:
        """The BLER this link level uses for ``mcs`` at ``sinr_db`` and code-block size
        ``cb_size`` (Sionna's interpolated NR PDSCH table ``mcs_table``)."""
        sinr = to_torch(10 ** (sinr_db / 10), self.device, self._torch.float32)
        return float(self.phy.get_bler(mcs, self.s.mcs_table, self.s.mcs_category, cb_size, sinr))

    def ensure(self, n_ue: int) -> None:
        if n_ue > self.capacity:
            self._grow(max(n_ue, 2 * self.capacity))

    def moved(self, u: int, new_cell: int) -> None:
        """UE column ``u`` now belongs to ``new_cell``: a fresh PF history there."""
        if self._sys is not None:
            adapter.reset_scheduler_history(self.pf, u, new_cell)
            self.rate_last[..., u] = 0.0

    def released(self, u: int) -> None:
        """Column ``u`` is free again (its UE left): its state goes back to new."""
        if self._sys is not None:
            adapter.reset_scheduler_history(self.pf, u)
            self.rate_last[..., u] = 0.0
            adapter.reset_link_adaptation(self.olla, u)
            self.harq[..., u] = -1

    def run(self, sinr_db: np.ndarray, serving: np.ndarray, backlog: Any = None) -> SlotResults:
        """Runs ``sinr_db.shape[0]`` slots. ``sinr_db``: SINR of each UE on its serving cell, [n_slots, n_ue] (wideband)
        or [n_slots, n_ue, subbands]; ``serving``: [n_ue] cell index (-1: no service). ``backlog``: the bits each UE
        has to receive (:class:`~caviar_plugins.network.traffic.Backlog`: queued at the first slot, and arriving per
        slot); None: full buffer. With a backlog a UE is scheduled only in slots (groups of ``harq_processes`` slots)
        that begin with bits queued, and what it decodes beyond its queue is padding: ``delivered_bits`` counts only
        the queue's bits."""
        sinr_db = self._checked_db(sinr_db)
        return self._one_link().run_links([sinr_db], serving, sinr_db.shape[0], [backlog])[0]

    def run_linear(self, sinr: Any, serving: np.ndarray, slots: int, backlog: Any = None) -> SlotResults:
        """:meth:`run` on linear SINRs as a torch tensor, [n_slots or 1 (every slot's), n_ue,
        subbands] (NaN: a UE without a cell): they become the link level's float32 SINRs where
        they are, without a way through numpy (at 1,000 UEs a step's are millions), the same
        float32 numbers as :meth:`run` makes of their dB. ``slots``: the slots to run."""
        return self._one_link().run_links([sinr], serving, slots, [backlog])[0]

    def run_links(self, sinrs: Sequence[Any], serving: np.ndarray, slots: int,
                  backlogs: Sequence[Any] | None = None) -> list[SlotResults]:
        """Runs ``slots`` slots of every link at once (the links' order: the settings'), each link's results in that
        order. Each link's SINRs as :meth:`run` takes them (numpy, dB, [slots, n_ue] or [slots, n_ue, subbands]) or as
        :meth:`run_linear` does (a torch tensor of ratios); ``serving`` [n_ue]: every link's; ``backlogs``: each
        link's (None: full buffers). A link with nobody queued in a group of slots sits it out (no transmission, no
        loop updates), whatever the others do."""
        if len(sinrs) != len(self.links):
            raise ValueError(f"sinrs: expected the SINRs of {len(self.links)} link(s) "
                             f"({', '.join(s.direction for s in self.links)}), got {len(sinrs)}")
        backlogs = [None] * len(sinrs) if backlogs is None else list(backlogs)
        if len(backlogs) != len(sinrs):
            raise ValueError(f"backlogs: expected {len(sinrs)} (one a link, None: full buffer), got {len(backlogs)}")
        ins = [self._checked_in(x, slots) for x in sinrs]
        n_ue = ins[0].shape[1]
        if any(x.shape[1] != n_ue for x in ins):
            raise ValueError(f"sinrs: expected every link's SINRs for the same UEs, got {[x.shape[1] for x in ins]}")
        self.ensure(n_ue)
        queues = [_Queue(slots, n_ue, b) for b in backlogs]
        if self._sys is None:
            return [shannon_slots(self.s, self.n_cell, self._db(x, slots), serving, q)
                    for x, q in zip(ins, queues, strict=True)]
        return self._sys_slots([self._linear_in(x, serving, slots) for x in ins], serving, queues)

    def _one_link(self) -> LinkLevel:
        if len(self.links) != 1:
            raise ValueError(f"this link level runs {len(self.links)} links together: call run_links")
        return self

    def _checked_db(self, sinr_db: Any) -> np.ndarray:
        sinr_db = np.asarray(sinr_db, dtype=float)
        if sinr_db.ndim == 2:
            sinr_db = np.broadcast_to(sinr_db[..., None], (*sinr_db.shape, self.s.subbands))
        if sinr_db.ndim != 3 or sinr_db.shape[2] != self.s.subbands:
            raise ValueError(f"sinr_db: expected [n_slots, n_ue] or [n_slots, n_ue, {self.s.subbands}], "
                             f"got shape {sinr_db.shape}")
        return sinr_db

    def _checked_in(self, x: Any, slots: int) -> Any:
        """One link's SINRs, checked: numpy dB [slots, n_ue, subbands], or a torch tensor of
        ratios [slots or 1, n_ue, subbands]."""
        if isinstance(x, np.ndarray) or not hasattr(x, "device"):
            x = self._checked_db(x)
            if x.shape[0] != slots:
                raise ValueError(f"sinr_db: expected {slots} slots, got shape {x.shape}")
            return x
        if x.ndim != 3 or x.shape[2] != self.s.subbands or x.shape[0] not in (1, slots):
            raise ValueError(f"sinr: expected [{slots} or 1, n_ue, {self.s.subbands}], got shape {tuple(x.shape)}")
        return x

    @staticmethod
    def _db(x: Any, slots: int) -> np.ndarray:
        """One link's checked SINRs in dB, [slots, n_ue, subbands] (the Shannon model's)."""
        if isinstance(x, np.ndarray):
            return x
        with np.errstate(divide="ignore", invalid="ignore"):
            db = 10 * np.log10(to_numpy(x))
        return np.broadcast_to(db, (slots, *db.shape[1:]))

    def _linear_in(self, x: Any, serving: np.ndarray, slots: int) -> Any:
        """The link level's float32 linear SINRs [slots, subbands, capacity] on its device, from one link's checked
        SINRs: dB in numpy (NaN: none; 0 for a UE without a cell), or ratios as a torch tensor (moved where the link
        level is, never through numpy)."""
        torch, dev = self._torch, self.device
        served = np.asarray(serving) >= 0
        if not isinstance(x, np.ndarray):
            n_ue, n_sub = x.shape[1], x.shape[2]
            lin = torch.zeros((x.shape[0], n_sub, self.capacity), dtype=torch.float32, device=dev)
            lin[:, :, :n_ue] = torch.where(to_torch(served, dev)[None, :, None], x.to(dev), 0.0).transpose(1, 2)
            if x.shape[0] != slots:  # (every slot the same SINRs: repeated on the device)
                lin = lin.expand(slots, n_sub, self.capacity).contiguous()
            return lin
        n_slots, n_ue, n_sub = x.shape
        # Every slot the same SINRs (a broadcast, as a flat channel's): converted once, repeated on the device.
        same = n_slots > 1 and x.strides[0] == 0
        lin = np.zeros((1 if same else n_slots, n_sub, self.capacity))
        block = np.nan_to_num(x[:1] if same else x, nan=-300.0).transpose(0, 2, 1)  # [slot, S, n_ue]
        lin[:, :, :n_ue] = np.where(served[None, None, :], 10 ** (block / 10), 0.0)
        lin_all = to_torch(lin, dev, torch.float32)  # (the call's one way in)
        return lin_all.expand(n_slots, n_sub, self.capacity).contiguous() if same else lin_all

    def _sys_slots(self, lins: list, serving: np.ndarray, queues: list[_Queue]) -> list[SlotResults]:
        """The slots through Sionna SYS, on each link's linear SINRs ``lins`` [n_slots, subbands, capacity] (float32, on
        the device: :meth:`_linear_in`). Everything stays on the link level's device from the first slot to the last:
        the call's SINRs enter torch once, the scheduler, the loops, the queues and the tallies work there, and the
        results leave once, at the end (on a GPU, no copy and no wait per slot; with queues, one read per group of
        slots says which links have bits)."""
        torch = self._torch
        n_links = len(lins)
        n_slots, n_ue = queues[0].delivered.shape
        d, cap, n_cell, dev = self.s.harq_processes, self.capacity, self.n_cell, self.device
        if n_slots % d:
            raise ValueError(f"{n_slots} slots are not whole groups of harq_processes = {d}")
        serving = np.asarray(serving)
        member = np.zeros((n_links, n_cell, cap), dtype=bool)
        on = np.flatnonzero(serving >= 0)
        member[:, serving[on], on] = True
        member_all = to_torch(member, dev)  # [L, C, cap]: whom each link's cell may schedule
        finite = any(q.finite for q in queues)
        for q in queues:
            q.on_device(dev, torch, cap)
        groups: list[tuple] = []  # each group's slots, as tensors: tallied once, after the loop
        # Each group's slots [L, D, S, cap] and first slot, made at once (tensors: no recompiling,
        # and no torch operation per group outside the compiled one).
        # [G, L, D, S, cap], the same strides whatever G (dynamo guards them); one link's: no copy
        shape = (n_slots // d, 1, d, *lins[0].shape[1:])
        lin_all = lins[0].view(shape) if n_links == 1 else torch.stack([x.view(shape) for x in lins], dim=1)[:, :, 0]
        # With full buffers, groups_per_call groups a compiled call (the ones left over: one a call).
        many = self.s.groups_per_call if self._many is not None and not finite else 1
        in_many = n_slots // d // many * many if many > 1 else 0
        plan = _CallPlan(d, queues, finite, member_all, self._all_links, lin_all.unbind(),
                         torch.arange(0, n_slots, d, device=dev).unbind(), many, in_many,
                         lin_all[:in_many].view(-1, many, *lin_all.shape[1:]).unbind() if in_many else (),
                         torch.arange(0, in_many * d, d, device=dev).view(-1, many).unbind() if in_many else (),
                         self._no_tallies)
        start = 0
        while start < n_slots:
            try:
                with self._guards(), self._own_stream():
                    for k in range(start, n_slots, d):
                        start = k  # (where a call that fails to find its entry starts again)
                        groups += self._groups_at(k, plan)
                start = n_slots
            except RuntimeError as e:  # (torch's refusal to compile while checking fewer guards)
                if not self._settled() or "skip_guard_eval_unsafe" not in str(e):
                    raise
                self._checked = 0  # (that group again, and the next calls, under every guard)
        if self._checked < CHECKED_CALLS:
            self._checked += len(groups)
        return tallied(self._torch, groups, queues, n_slots, n_ue, self.n_cell)

    def _groups_at(self, k: int, plan: _CallPlan) -> list[tuple]:
        """The slots a call at slot ``k`` runs, ``(first slot, slots, PRBs, HARQ, TBLER, MCS, effective SINR, cells
        active, decoded bits, tallies)``, each [L, slots, ...] (the tallies
        :func:`~caviar_plugins.radio.slot_results.per_ue` of the call's slots up to the chunk's last, carried from
        chunk to chunk; None for one group): a chunk of ``plan.many`` groups at its first group (none at its others),
        else the group at ``k`` (none where no link has bits)."""
        torch, g = self._torch, k // plan.d
        if g < plan.in_many:
            if g % plan.many:
                return []  # (run with its chunk)
            c = g // plan.many
            *fields, plan.tallies, self.harq, self.rate_last = self._groups(
                plan.chunks[c], plan.member, plan.chunk_firsts[c], self.harq, self.rate_last, plan.went, plan.tallies)
            # (each field [L, many · D, ...]: the chunk's slots in order; then the tallies so far)
            return [(k, plan.many * plan.d, *fields, plan.tallies)]
        member_t, went, ran = plan.member, plan.went, None
        if plan.finite:  # (only UEs with bits queued at the group's first slot)
            member_t = plan.member & torch.stack([q.eligible(k) for q in plan.queues])[:, None, :]
            went = member_t.any(dim=2).any(dim=1)
            ran = went.tolist()  # (the group's one read)
            if not any(ran):
                return []  # nothing to send: no call (no transmission, no loop updates)
        prbs, harq, tbler, mcs, sinr_eff, cells, bits, self.harq, self.rate_last = self._group(
            plan.blocks[g], member_t, plan.firsts[g], self.harq, self.rate_last, went)
        for q, link_bits, link_ran in zip(plan.queues, bits, ran or (), strict=False):
            if q.finite and link_ran:
                q.take_group(k, link_bits.to(torch.float64))
        return [(k, plan.d, prbs, harq, tbler, mcs, sinr_eff, cells, bits, None)]

    def _guards(self) -> Any:
        """A context (for the call's groups only): how dynamo checks the compiled group's calls: every guard of its
        entries (over 400: the Sionna blocks' attributes, the settings, the tensors' shapes) for the first
        :data:`CHECKED_CALLS` calls at a UE capacity, which compile what they need (two entries: before and after
        Sionna builds its blocks); then only the guards that tell the entries apart
        (``torch.compiler.set_stance(skip_guard_eval_unsafe=True)``). At 21 cells × 1,000 UEs (then 50 calls a step: a
        link level a direction) on a 2-core Intel Xeon the guards took 13.5 ms of host time a step checked in full and
        6.4 ms so (``benches/bench_host_overhead.py``: host work on a GPU too), with the same results bit for bit
        (tests/test_network.py); fewer calls (both links in one, ``groups_per_call``) cut them further. What could
        change a guard's outcome between this link level's calls at one capacity, its blocks and tensors made anew,
        resets the count (:meth:`_grow`, :meth:`restore`); and where torch would have to compile (it refuses to in
        this stance), the group runs again under every guard, and the count starts again. The stance is the process's
        while the call's groups run (the host calls one plugin at a time)."""
        if not self._settled():
            return contextlib.nullcontext()
        # (set_stance sets the stance when called, and puts the last one back when its block ends)
        return self._torch.compiler.set_stance("default", skip_guard_eval_unsafe=True)

    def _settled(self) -> bool:
        """Whether the compiled group's calls check only the guards that tell its entries apart
        (:meth:`_guards`)."""
        return self._compiled is not None and self._checked >= CHECKED_CALLS

    @contextlib.contextmanager
    def _own_stream(self) -> Iterator[None]:
        """The compiled groups of a call drawing from the link level's own stream: their random numbers come from the
        device's default generator (what compiled code draws from), with this link level's state swapped in for the
        call's groups (nothing else draws between them) and the caller's put back. (Eager groups draw from the link
        level's generator, and a captured CUDA graph replays the generator it captured: nothing to swap.)"""
        if self._compiled is None or self.cuda_graphs:
            yield
            return
        generator = default_generator(self.device)
        caller = generator.get_state()
        generator.set_state(self._compiled_rng)
        try:
            yield
        finally:
            self._compiled_rng = generator.get_state()
            generator.set_state(caller)

    def _group_graphed(self, *args):
        """The compiled group replayed as a CUDA graph: a new step of the graph's memory, its outputs
        and the OLLA's state copied out (the next replay writes over the graph's own: the H200's failure).
        Where torch refuses a replay (its CUDA graphs' error, raised before the graph runs), the link
        level goes on compiled without graphs, and says so."""
        self._torch.compiler.cudagraph_mark_step_begin()
        try:
            outputs = tuple(o.clone() for o in self._compiled(*args))
        except RuntimeError as e:
            if "CUDAGraph" not in str(e):
                raise
            print(f"link level: a CUDA graph's replay failed ({e}); going on compiled without graphs",
                  file=sys.stderr, flush=True)
            self.cuda_graphs = False
            self._compiled = self._group = self._torch.compile(self._group_eager, dynamic=False)
            return self._group(*args)
        adapter.copy_out_link_adaptation(self.olla)
        return outputs

    def _groups(self, *args):
        """:meth:`_groups_eager`, compiled; past torch's limit of compiled entries (one graph: no eager
        fallback) the chunk's groups one a call, the same results."""
        try:
            return self._many(*args)
        except Exception as e:
            if not adapter.past_recompile_limit(e):
                raise
            return link_chunks.unrolled(self._group, *args)

    def _groups_eager(self, *args):
        """A chunk of groups as one loop (:func:`~caviar_plugins.radio.link_chunks.scanned`)."""
        pf_schedules = self.s.scheduler == "proportional-fair"
        return link_chunks.scanned(self._group_eager, (self.olla, self.pf, pf_schedules), *args)

    def _group_eager(self, lin_t, member_t, first_slot, harq_last, rate_last, went, loops=None):
        """One group of D slots of every link, all on the device: scheduling, CSI, link adaptation and PHY abstraction.
        ``lin_t`` [L, D, S, cap]: linear SINRs; ``member_t`` [L, C, cap]: whom each link's cell may schedule;
        ``first_slot``: the group's first slot (a 0-d tensor); ``harq_last`` [L, D, cap] and ``rate_last`` [L, D, C,
        cap]: the state the group starts from; ``went`` [L]: the links that take part (the others keep their state).
        ``loops``: the OLLA and PF blocks to run (None: the link level's own). Returns (PRBs, HARQ, TBLER, MCS,
        effective SINR, each [L, D, cap]; the cells that transmitted [L, D, C]; decoded bits [L, D, cap]; the new
        ``harq_last`` and ``rate_last``)."""
        torch = self._torch
        olla, pf = loops or (self.olla, self.pf)
        kept = adapter.loop_state(olla, pf)  # (for the links that sit the group out)
        # Achievable rate per PRB of each UE in its own cell (bit/s/Hz); 0 elsewhere.
        rate = torch.log2(1 + lin_t)[:, :, None] * member_t[:, None, :, None, :]  # [L, D, C, S, cap]
        granted = self._schedule(rate, member_t, first_slot, rate_last, pf)  # [L, D, C, S, cap] bool
        alloc = granted.any(dim=2)  # [L, D, S, cap]: a UE is in one cell
        prbs = (alloc * self._prb_weights[:, None]).sum(dim=2).to(torch.int32)  # [L, D, cap]
        n_re = prbs * (12 * DATA_SYMBOLS_PER_SLOT)
        if self.s.subbands == 1:
            csi, sinr_in = lin_t[:, :, 0], lin_t[:, :, 0]
        else:
            csi, sinr_in = self._subband_sinr(lin_t, alloc)
        mcs, bits, harq, sinr_eff, tbler = self._adapt_and_decode(n_re, harq_last, csi, sinr_in, olla)
        # The rate each cell achieved for each UE, for the PF history.
        rate_new = bits.to(torch.float32)[:, :, None, :] / self.s.slot_s * member_t[:, None]
        adapter.keep_loop_state(olla, pf, kept, went)
        harq_next = torch.where(went[:, None, None], harq, harq_last)
        rate_next = torch.where(went[:, None, None, None], rate_new, rate_last)
        cells = granted.any(dim=4).any(dim=3)  # [L, D, C]
        return prbs, harq, tbler, mcs, sinr_eff, cells, bits, harq_next, rate_next

    def _adapt_and_decode(self, n_re, harq_last, csi, sinr_in, olla):
        """Link adaptation and PHY abstraction: (MCS, decoded bits, HARQ, effective SINR, TBLER), each [L, D, cap].
        ``sinr_in``: the wideband SINR [L, D, cap], or the allocated PRBs' [L, D, 1, P, cap, 1] for the EESM."""
        # CSI feedback: the slot's SINR as the UE reports it (ideal), corrected by the
        # loop's offset, which follows the HARQ outcome of the process's last transmission.
        table, category = self._mcs_table, self._mcs_category  # (each link's: numbers, or [L, D, cap])
        mcs = olla(n_re, harq_last, csi, mcs_table_index=table, mcs_category=category)
        if sinr_in.dim() > 3:  # EESM over the allocated PRBs, with the MCS's own beta
            sinr_in = self.eesm(sinr_in, mcs_index=mcs, mcs_table_index=table, mcs_category=category,
                                per_stream=False)
        bits, harq, sinr_eff, tbler, _ = self.phy(
            mcs, sinr_eff=sinr_in, num_allocated_re=n_re, mcs_table_index=table, mcs_category=category)
        return mcs, bits, harq, sinr_eff, tbler

    def _subband_sinr(self, lin_t, alloc):
        """The CSI a UE reports, its allocated subbands' SINR averaged in dB weighted by
        their PRBs (all subbands when it has none), [L, D, cap]; and the SINR of every PRB it
        was allocated (0 elsewhere), the EESM's input [L, D, 1, P, cap, 1]."""
        torch = self._torch
        w = self._prb_weights[:, None] * torch.where(alloc.any(dim=2, keepdim=True), alloc, True)
        db = 10 * torch.log10(torch.clamp(lin_t, min=1e-30))
        csi = 10 ** ((w * db).sum(dim=2) / w.sum(dim=2) / 10)
        per_prb = (lin_t * alloc)[:, :, self._prb_subband]  # [L, D, P, cap]
        return csi, per_prb[:, :, None, :, :, None]

    def _schedule(self, rate, member, first_slot, rate_last, pf):
        """[L, D, C, S, cap]: which UE gets each subband of each link's cell in each slot of the
        group. ``member`` [L, C, cap]: the UEs each cell may schedule (a tensor on the device);
        ``first_slot``: the group's first slot (a 0-d tensor); ``rate_last``: the rate each
        cell achieved for each UE at the process's last slot, [L, D, C, cap]; ``pf``: the PF scheduler."""
        torch = self._torch
        d, n_sub = self.s.harq_processes, self.s.subbands
        cells = member[:, None, :, None, :]  # [L, 1, C, 1, cap]
        if self.s.scheduler == "proportional-fair":
            granted = pf(rate_last, rate[:, :, :, None])[:, :, :, 0, :, :, 0]  # [L, D, C, S, cap]
            # A cell without UEs: the argmax picked column 0, which is not its UE.
            return granted & cells
        if self.s.scheduler == "max-rate":  # per subband, the member with the best rate (the first of equals)
            best = torch.argmax(torch.where(cells, rate, -1.0), dim=4)  # [L, D, C, S]
            pick = torch.arange(member.shape[2], device=self.device) == best[..., None]
            return pick & cells  # (a cell without members grants nothing)
        # round-robin: one UE per slot, the cell's members in turn
        rank = torch.cumsum(member.to(torch.int64), dim=2) - 1  # [L, C, cap]: place among the cell's members
        count = torch.clamp(member.sum(dim=2), min=1)  # [L, C]
        turn = (first_slot + torch.arange(d, device=self.device))[None, :, None] % count[:, None, :]  # [L, D, C]
        pick = member[:, None] & (rank[:, None] == turn[..., None])  # [L, D, C, cap]
        return pick[:, :, :, None, :].expand(*pick.shape[:3], n_sub, pick.shape[3])
