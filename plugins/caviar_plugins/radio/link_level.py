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
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from typing import Any, Iterator

import numpy as np

from caviar_plugins.radio.link_queue import CallQueue as _Queue
from caviar_plugins.radio.link_settings import DATA_SYMBOLS_PER_SLOT, LinkSettings, cuda_graphs_on
from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.torch_device import resolve, to_numpy, to_torch

COMPILED_CAPACITY = 128
"""UE columns a compiled link level starts with (growing past them compiles again)."""
CHECKED_CALLS = 8
"""Calls of a compiled group of slots that dynamo checks in full (every guard of its compiled
entries) at a UE capacity, after which the link level's further calls there check only the guards
that tell the entries apart (:meth:`LinkLevel._guards`)."""


@dataclasses.dataclass
class SlotResults:
    """What a UE got over the slots of one call."""

    decoded_bits: np.ndarray  # [n_ue] summed over the slots
    scheduled_slots: np.ndarray  # [n_ue] slots with at least one PRB
    prbs: np.ndarray  # [n_ue] PRB-slots allocated
    acks: np.ndarray  # [n_ue]
    nacks: np.ndarray  # [n_ue]
    mcs: np.ndarray  # [n_ue] the last MCS used (-1: never scheduled)
    tbler: np.ndarray  # [n_ue] mean TBLER over scheduled slots (NaN: none)
    sinr_eff_db: np.ndarray  # [n_ue] the last effective SINR (NaN: none)
    cells_active: np.ndarray  # [n_slots, n_cell] cells that scheduled someone
    delivered_bits: np.ndarray  # [n_slots, n_ue] bits decoded per slot (of the UE's queue)

    def bler(self, ue: int) -> float:
        return self.nacks[ue] / max(self.acks[ue] + self.nacks[ue], 1)

    def throughput_bps(self, n_slots: int, slot_s: float) -> np.ndarray:
        return self.decoded_bits / (n_slots * slot_s)

    def summary(self, u: int) -> dict[str, Any]:
        return {"mcs": int(self.mcs[u]),
                "tbler": None if np.isnan(self.tbler[u]) else round(float(self.tbler[u]), 4),
                "harq_ack": int(self.acks[u]), "harq_nack": int(self.nacks[u]),
                "prbs": int(self.prbs[u])}


class LinkLevel:
    """Scheduling, link adaptation and PHY abstraction for ``n_cell`` cells."""

    def __init__(self, settings: LinkSettings, n_cell: int, seed: int = 0, capacity: int = 8):
        self.s = settings
        self.n_cell = n_cell
        self.capacity = 0
        self.seed = seed
        self._sys: Any = None
        self.olla: Any = None
        self.pf: Any = None
        self.harq: Any = None
        self.rate_last: Any = None
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
        self._group = self._group_eager
        self._compiled: Any = None
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
            if self.cuda_graphs:  # (a captured graph replays the device generator it captured: seeded here)
                adapter.default_generator(self.device).set_state(self._compiled_rng)
            # Each UE capacity and each direction compiles its own entries (two each: before and
            # after Sionna's blocks are built); past torch's limit (8) it would fall back to eager.
            adapter.allow_recompiles(self._torch, 64)
            capacity = max(capacity, COMPILED_CAPACITY)  # each growth compiles again
            print(f"link level: torch.compile for {capacity} UEs at the first slots (about 20 s, once)",
                  file=sys.stderr, flush=True)
        self._grow(capacity)

    def _grow(self, capacity: int) -> None:
        """Room for ``capacity`` UEs, keeping the state of the first ``self.capacity``.
        State, per HARQ process d: OLLA offset and last SINR [D, cap], PF history
        [D, cell, cap], last HARQ outcome [D, cap] and achieved rate [D, cell, cap]."""
        old = self.capacity
        self.capacity = capacity
        self._checked = 0  # (new blocks, new shapes: checked in full again)
        if self._sys is None:
            return
        torch = self._torch
        d, c = self.s.harq_processes, self.n_cell
        olla = self._sys.OuterLoopLinkAdaptation(self.phy, num_ut=capacity, bler_target=self.s.bler_target,
                                                 batch_size=[d], device=str(self.device))
        # The PF metric is the same on every PRB of a subband, so Sionna's scheduler decides
        # on one resource per subband, standing for its PRBs.
        pf = self._sys.PFSchedulerSUMIMO(capacity, self.s.subbands, 1, batch_size=[d, c], device=str(self.device))
        harq = torch.full((d, capacity), -1, dtype=torch.int32, device=self.device)
        rate_last = torch.zeros(d, c, capacity, device=self.device)
        if old:
            adapter.grow_link_adaptation(olla, self.olla, old)
            adapter.grow_scheduler(pf, self.pf, old)
            harq[:, :old], rate_last[:, :, :old] = self.harq, self.rate_last
        self.olla, self.pf, self.harq, self.rate_last = olla, pf, harq, rate_last

    def state(self) -> dict[str, Any]:
        """What changes from slot to slot, for a checkpoint: the capacity, every tensor
        the OLLA loops and the PF scheduler keep, the HARQ outcomes, the achieved rates and
        the position of Sionna's random stream (the PHY abstraction's ACK draws)."""
        if self._sys is None:
            return {"capacity": self.capacity}
        return {"capacity": self.capacity,
                "olla": adapter.block_state(self.olla), "pf": adapter.block_state(self.pf),
                "harq": self.harq.clone(), "rate_last": self.rate_last.clone(),
                "rng": self._generator.get_state(), "compiled_rng": self._compiled_rng.clone()}

    def restore(self, state: dict[str, Any]) -> None:
        """Puts back :meth:`state` into a link level built with the same settings."""
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
            self.rate_last[:, :, u] = 0.0

    def released(self, u: int) -> None:
        """Column ``u`` is free again (its UE left): its state goes back to new."""
        if self._sys is not None:
            adapter.reset_scheduler_history(self.pf, u)
            self.rate_last[:, :, u] = 0.0
            adapter.reset_link_adaptation(self.olla, u)
            self.harq[:, u] = -1

    def run(self, sinr_db: np.ndarray, serving: np.ndarray, backlog: Any = None) -> SlotResults:
        """Runs ``sinr_db.shape[0]`` slots. ``sinr_db``: SINR of each UE on its serving
        cell, [n_slots, n_ue] (wideband) or [n_slots, n_ue, subbands]; ``serving``: [n_ue]
        cell index (-1: no service). ``backlog``: the bits each UE has to receive
        (:class:`~caviar_plugins.network.traffic.Backlog`: queued at the first slot, and
        arriving per slot); None: full buffer. With a backlog a UE is scheduled only in slots
        (groups of ``harq_processes`` slots) that begin with bits queued, and what it decodes
        beyond its queue is padding: ``delivered_bits`` counts only the queue's bits."""
        sinr_db = np.asarray(sinr_db, dtype=float)
        if sinr_db.ndim == 2:
            sinr_db = np.broadcast_to(sinr_db[..., None], (*sinr_db.shape, self.s.subbands))
        if sinr_db.ndim != 3 or sinr_db.shape[2] != self.s.subbands:
            raise ValueError(f"sinr_db: expected [n_slots, n_ue] or [n_slots, n_ue, {self.s.subbands}], "
                             f"got shape {sinr_db.shape}")
        n_slots, n_ue, _ = sinr_db.shape
        self.ensure(n_ue)
        queue = _Queue(n_slots, n_ue, backlog)
        if self._sys is None:
            return self._shannon(sinr_db, serving, queue)
        return self._sys_slots(self._linear_in(sinr_db, serving), serving, queue)

    def run_linear(self, sinr: Any, serving: np.ndarray, slots: int, backlog: Any = None) -> SlotResults:
        """:meth:`run` on linear SINRs as a torch tensor, [n_slots or 1 (every slot's), n_ue,
        subbands] (NaN: a UE without a cell): they become the link level's float32 SINRs where
        they are, without a way through numpy (at 1,000 UEs a step's are millions), the same
        float32 numbers as :meth:`run` makes of their dB. ``slots``: the slots to run."""
        n_ue, n_sub = sinr.shape[1], sinr.shape[2]
        if sinr.ndim != 3 or n_sub != self.s.subbands or sinr.shape[0] not in (1, slots):
            raise ValueError(f"sinr: expected [{slots} or 1, n_ue, {self.s.subbands}], got shape {tuple(sinr.shape)}")
        self.ensure(n_ue)
        queue = _Queue(slots, n_ue, backlog)
        if self._sys is None:
            with np.errstate(divide="ignore", invalid="ignore"):
                db = 10 * np.log10(to_numpy(sinr))
            return self._shannon(np.broadcast_to(db, (slots, n_ue, n_sub)), serving, queue)
        torch, dev = self._torch, self.device
        x = sinr.to(dev)
        lin = torch.zeros((x.shape[0], n_sub, self.capacity), dtype=torch.float32, device=dev)
        lin[:, :, :n_ue] = torch.where(to_torch(np.asarray(serving) >= 0, dev)[None, :, None], x, 0.0).transpose(1, 2)
        if x.shape[0] != slots:  # (every slot the same SINRs: repeated on the device)
            lin = lin.expand(slots, n_sub, self.capacity).contiguous()
        return self._sys_slots(lin, serving, queue)

    def _linear_in(self, sinr_db: np.ndarray, serving: np.ndarray) -> Any:
        """The link level's float32 linear SINRs [n_slots, subbands, capacity] on its device,
        from dB [n_slots, n_ue, subbands] (NaN: none; 0 for a UE without a cell)."""
        torch = self._torch
        n_slots, n_ue, n_sub = sinr_db.shape
        # Every slot the same SINRs (a broadcast, as a flat channel's): converted once, repeated on the device.
        same = n_slots > 1 and sinr_db.strides[0] == 0
        lin = np.zeros((1 if same else n_slots, n_sub, self.capacity))
        block = np.nan_to_num(sinr_db[:1] if same else sinr_db, nan=-300.0).transpose(0, 2, 1)  # [slot, S, n_ue]
        lin[:, :, :n_ue] = np.where((np.asarray(serving) >= 0)[None, None, :], 10 ** (block / 10), 0.0)
        lin_all = to_torch(lin, self.device, torch.float32)  # (the call's one way in)
        return lin_all.expand(n_slots, n_sub, self.capacity).contiguous() if same else lin_all

    def _shannon(self, sinr_db: np.ndarray, serving: np.ndarray, queue: _Queue) -> SlotResults:
        n_slots, n_ue, _ = sinr_db.shape
        band = self.s.subband_prbs * self.s.prb_bandwidth_hz  # [subbands]
        se = np.log2(1 + 10 ** (np.nan_to_num(sinr_db, nan=-np.inf) / 10))
        rate = (se * band).sum(axis=2) * self.s.slot_s  # [slot, ue] bits with the whole cell
        active = np.zeros((n_slots, self.n_cell), dtype=bool)
        sched = np.zeros(n_ue)
        if not queue.finite:  # a full buffer: every slot alike, one share for all (no slot loop)
            counts, share = self._time_shares(serving >= 0, serving)
            queue.delivered[:] = rate * share
            active[:, counts > 0] = True
            sched += np.where(serving >= 0, n_slots, 0)
        else:  # queues: slot by slot, among the UEs with bits
            for k in range(n_slots):
                eligible = (serving >= 0) & queue.eligible(k)
                counts, share = self._time_shares(eligible, serving)
                queue.take(k, rate[k] * share)
                active[k, counts > 0] = True
                sched += eligible
        zeros = np.zeros(n_ue, dtype=int)
        known = ~np.isnan(sinr_db)
        count = known.sum(axis=(0, 2))  # (a UE without a cell has no SINR: NaN, without a warning)
        mean = np.where(count > 0, np.where(known, sinr_db, 0.0).sum(axis=(0, 2)) / np.maximum(count, 1), np.nan)
        return SlotResults(queue.delivered.sum(axis=0), sched.astype(int), zeros, zeros, zeros,
                           np.full(n_ue, -1), np.full(n_ue, np.nan), mean, active, queue.delivered)

    def _time_shares(self, eligible: np.ndarray, serving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shannon's equal time shares: the UEs each cell serves among ``eligible`` [n_cell],
        and each UE's share of its cell's time [n_ue] (0: not eligible)."""
        counts = np.bincount(serving[eligible], minlength=self.n_cell)
        return counts, np.where(eligible, 1.0 / np.maximum(counts[np.maximum(serving, 0)], 1), 0.0)

    def _sys_slots(self, lin_all: Any, serving: np.ndarray, queue: _Queue) -> SlotResults:
        """The slots through Sionna SYS, on linear SINRs ``lin_all`` [n_slots, subbands,
        capacity] (float32, on the device: :meth:`_linear_in`). Everything stays on the link
        level's device from the first slot to the last: the call's SINRs enter torch once, the
        scheduler, the loops, the queues and the tallies work there, and the results leave once,
        at the end (on a GPU, no copy and no wait per slot; with queues, one flag per group of
        slots says whether anyone has bits)."""
        torch = self._torch
        n_slots, n_ue = queue.delivered.shape
        d, cap, n_cell, dev = self.s.harq_processes, self.capacity, self.n_cell, self.device
        if n_slots % d:
            raise ValueError(f"{n_slots} slots are not whole groups of harq_processes = {d}")
        serving = np.asarray(serving)
        member = np.zeros((n_cell, cap), dtype=bool)
        on = np.flatnonzero(serving >= 0)
        member[serving[on], on] = True
        member_all = to_torch(member, dev)
        queue.on_device(dev, torch, cap)
        groups: list[tuple] = []  # each group's slots, as tensors: tallied once, after the loop
        member_t = member_all
        # Each group's slots and first slot as views made at once (tensors: no recompiling, no copy,
        # and no torch operation per group outside the compiled one).
        firsts, blocks = torch.arange(0, n_slots, d, device=dev).unbind(), lin_all.split(d)
        start = 0
        while start < n_slots:
            try:
                with self._guards(), self._own_stream():
                    for k in range(start, n_slots, d):
                        start = k  # (where a call that fails to find its entry starts again)
                        if queue.finite:  # (only UEs with bits queued at the group's first slot)
                            member_t = member_all & queue.eligible(k)[None, :]
                            if not bool(member_t.any()):
                                continue  # nothing to send: no call (no transmission, no loop updates)
                        prbs, harq, tbler, mcs, sinr_eff, cells, bits, self.rate_last = self._group(
                            blocks[k // d], member_t, firsts[k // d], self.harq, self.rate_last)
                        self.harq = harq
                        if queue.finite:
                            queue.take_group(k, bits.to(torch.float64))
                        groups.append((k, prbs, harq, tbler, mcs, sinr_eff, cells, bits))
                start = n_slots
            except RuntimeError as e:  # (torch's refusal to compile while checking fewer guards)
                if not self._settled() or "skip_guard_eval_unsafe" not in str(e):
                    raise
                self._checked = 0  # (that group again, and the next calls, under every guard)
        if self._checked < CHECKED_CALLS:
            self._checked += len(groups)
        return self._tallied(groups, queue, n_slots, n_ue)

    def _guards(self) -> Any:
        """A context (for the call's groups only): how dynamo checks the compiled group's calls:
        every guard of its entries (over 400: the Sionna blocks' attributes, the settings, the
        tensors' shapes) for the first :data:`CHECKED_CALLS` calls at a UE capacity, which compile
        what they need (two entries: before and after Sionna builds its blocks); then only the
        guards that tell the entries apart (``torch.compiler.set_stance(skip_guard_eval_unsafe=True)``).
        At 21 cells × 1,000 UEs (50 calls a step) on a 2-core Intel Xeon the guards took 13.5 ms of
        host time a step checked in full and 6.4 ms so (``benches/bench_host_overhead.py``: host
        work on a GPU too), with the same results bit for bit (tests/test_network.py). What could
        change a guard's outcome between this link level's calls at one capacity, its blocks and
        tensors made anew, resets the count (:meth:`_grow`, :meth:`restore`); and where torch
        would have to compile (it refuses to in this stance), the group runs again under every
        guard, and the count starts again. The stance is the process's while the call's groups
        run (the host calls one plugin at a time)."""
        if not self._settled():
            return contextlib.nullcontext()
        # (set_stance sets the stance when called, and puts the last one back when its block ends)
        return self._torch.compiler.set_stance("default", skip_guard_eval_unsafe=True)

    def _settled(self) -> bool:
        """Whether the compiled group's calls check only the guards that tell its entries apart
        (:meth:`_guards`)."""
        return self._compiled is not None and self._checked >= CHECKED_CALLS

    def _tallied(self, groups: list[tuple], queue: _Queue, n_slots: int, n_ue: int) -> SlotResults:
        """The call's results from its groups of slots (tallied on the device, then the
        call's one way out)."""
        torch, dev = self._torch, self.device
        if not groups:
            zeros = np.zeros(n_ue, dtype=int)
            return SlotResults(np.zeros(n_ue), zeros, zeros, zeros, zeros, np.full(n_ue, -1), np.full(n_ue, np.nan),
                               np.full(n_ue, np.nan), np.zeros((n_slots, self.n_cell), dtype=bool),
                               np.zeros((n_slots, n_ue)))
        d = self.s.harq_processes  # (every group is d slots)
        prbs, harq, tbler, mcs, sinr_eff, cells, bits = map(torch.cat, list(zip(*groups, strict=True))[1:])
        delivered = queue.delivered
        if len(groups) * d == n_slots:  # (every group ran: the slots in order)
            active = cells
            if not queue.finite:  # (a full buffer delivers all it decodes)
                delivered = bits.to(torch.float64)
        else:
            slots = torch.cat([torch.arange(g[0], g[0] + d, device=dev) for g in groups])
            active = torch.zeros((n_slots, self.n_cell), dtype=torch.bool, device=dev)
            active[slots] = cells
            if not queue.finite:
                delivered[slots] = bits.to(torch.float64)
        sched = prbs > 0  # [slots run, cap]
        # the last scheduled slot's MCS and effective SINR
        last = (len(sched) - 1 - torch.argmax(torch.flip(sched, (0,)).to(torch.uint8), dim=0))[None]  # [1, cap]
        anyone = sched.any(dim=0)
        mcs_last = torch.where(anyone, mcs.to(torch.int64).gather(0, last)[0], -1)
        eff_db = 10 * torch.log10(torch.clamp(sinr_eff.to(torch.float64).gather(0, last)[0], min=1e-30))
        sinr_eff_last = torch.where(anyone, eff_db, float("nan"))
        tbler_sum = torch.where(sched, tbler.to(torch.float64), 0.0).sum(dim=0)
        # (the call's one way out: every tally, as float64 (the counts exact in it), in one read)
        per_ue = torch.stack([sched.sum(dim=0), prbs.sum(dim=0), (harq == 1).sum(dim=0), (harq == 0).sum(dim=0),
                              tbler_sum, mcs_last, sinr_eff_last]).to(torch.float64)
        out = to_numpy(torch.cat([per_ue.flatten(), active.flatten(), delivered.flatten()]))
        cap = per_ue.shape[1]
        counts = out[:4 * cap].reshape(4, cap)[:, :n_ue].astype(np.int64)
        tbler_n, mcs_n, eff_n = out[4 * cap:7 * cap].reshape(3, cap)[:, :n_ue]
        active_n = out[7 * cap:7 * cap + active.numel()].reshape(active.shape) != 0
        delivered = out[7 * cap + active.numel():].reshape(n_slots, cap)[:, :n_ue]
        sched_n, prbs_n, acks_n, nacks_n = counts
        with np.errstate(invalid="ignore", divide="ignore"):
            tbler_mean = np.where(sched_n > 0, tbler_n / sched_n, np.nan)
        return SlotResults(delivered.sum(axis=0), sched_n, prbs_n, acks_n, nacks_n, mcs_n.astype(np.int64),
                           tbler_mean, eff_n, active_n, delivered)

    @contextlib.contextmanager
    def _own_stream(self) -> Iterator[None]:
        """The compiled groups of a call drawing from the link level's own stream: their random
        numbers come from the device's default generator (what compiled code draws from), with
        this link level's state swapped in for the call's groups (nothing else draws between them)
        and the caller's put back. (Eager groups draw from the link level's generator, and a
        captured CUDA graph replays the generator it captured: nothing to swap.)"""
        if self._compiled is None or self.cuda_graphs:
            yield
            return
        generator = adapter.default_generator(self.device)
        caller = generator.get_state()
        generator.set_state(self._compiled_rng)
        try:
            yield
        finally:
            self._compiled_rng = generator.get_state()
            generator.set_state(caller)

    def _group_graphed(self, *args):
        """The compiled group replayed as a CUDA graph: a new step of the graph's memory,
        and its outputs copied out (the next replay writes over the graph's own)."""
        self._torch.compiler.cudagraph_mark_step_begin()
        return tuple(o.clone() for o in self._compiled(*args))

    def _group_eager(self, lin_t, member_t, first_slot, harq_last, rate_last):
        """One group of D slots, all on the device: scheduling, CSI, link adaptation and PHY
        abstraction. ``lin_t`` [D, S, cap]: linear SINRs; ``member_t`` [C, cap]: whom each
        cell may schedule; ``first_slot``: the group's first slot (a 0-d tensor);
        ``harq_last`` [D, cap] and ``rate_last`` [D, C, cap]: the state the group starts
        from. Returns (PRBs, HARQ, TBLER, MCS, effective SINR, each [D, cap]; the cells that
        transmitted [D, C]; decoded bits [D, cap]; the new ``rate_last``)."""
        torch = self._torch
        # Achievable rate per PRB of each UE in its own cell (bit/s/Hz); 0 elsewhere.
        rate = torch.log2(1 + lin_t)[:, None, :, :] * member_t[None, :, None, :]  # [D, C, S, cap]
        granted = self._schedule(rate, member_t, first_slot, rate_last)  # [D, C, S, cap] bool
        alloc = granted.any(dim=1)  # [D, S, cap]: a UE is in one cell
        prbs = (alloc * self._prb_weights[None, :, None]).sum(dim=1).to(torch.int32)  # [D, cap]
        n_re = prbs * (12 * DATA_SYMBOLS_PER_SLOT)
        if self.s.subbands == 1:
            csi, sinr_in = lin_t[:, 0], lin_t[:, 0]
        else:
            csi, sinr_in = self._subband_sinr(lin_t, alloc)
        mcs, bits, harq, sinr_eff, tbler = self._adapt_and_decode(n_re, harq_last, csi, sinr_in)
        # The rate each cell achieved for each UE, for the PF history.
        rate_last = bits.to(torch.float32)[:, None, :] / self.s.slot_s * member_t
        return prbs, harq, tbler, mcs, sinr_eff, granted.any(dim=3).any(dim=2), bits, rate_last

    def _adapt_and_decode(self, n_re, harq_last, csi, sinr_in):
        """Link adaptation and PHY abstraction: (MCS, decoded bits, HARQ, effective SINR,
        TBLER), each [D, cap]. ``sinr_in``: the wideband SINR [D, cap], or the allocated
        PRBs' [D, 1, P, cap, 1] for the EESM."""
        # CSI feedback: the slot's SINR as the UE reports it (ideal), corrected by the
        # loop's offset, which follows the HARQ outcome of the process's last transmission.
        mcs = self.olla(n_re, harq_last, csi, mcs_table_index=self.s.mcs_table, mcs_category=self.s.mcs_category)
        if sinr_in.dim() > 2:  # EESM over the allocated PRBs, with the MCS's own beta
            sinr_in = self.eesm(sinr_in, mcs_index=mcs, mcs_table_index=self.s.mcs_table,
                                mcs_category=self.s.mcs_category, per_stream=False)
        bits, harq, sinr_eff, tbler, _ = self.phy(
            mcs, sinr_eff=sinr_in, num_allocated_re=n_re, mcs_table_index=self.s.mcs_table,
            mcs_category=self.s.mcs_category)
        return mcs, bits, harq, sinr_eff, tbler

    def _subband_sinr(self, lin_t, alloc):
        """The CSI a UE reports, its allocated subbands' SINR averaged in dB weighted by
        their PRBs (all subbands when it has none), [D, cap]; and the SINR of every PRB it
        was allocated (0 elsewhere), the EESM's input [D, 1, P, cap, 1]."""
        torch = self._torch
        w = self._prb_weights[None, :, None] * torch.where(alloc.any(dim=1, keepdim=True), alloc, True)
        db = 10 * torch.log10(torch.clamp(lin_t, min=1e-30))
        csi = 10 ** ((w * db).sum(dim=1) / w.sum(dim=1) / 10)
        per_prb = (lin_t * alloc)[:, self._prb_subband]  # [D, P, cap]
        return csi, per_prb[:, None, :, :, None]

    def _schedule(self, rate, member, first_slot, rate_last):
        """[D, C, S, cap]: which UE gets each subband of each cell in each slot of the group.
        ``member`` [C, cap]: the UEs each cell may schedule (a tensor on the device);
        ``first_slot``: the group's first slot (a 0-d tensor); ``rate_last``: the rate each
        cell achieved for each UE at the process's last slot, [D, C, cap]."""
        torch = self._torch
        d, n_sub = self.s.harq_processes, self.s.subbands
        if self.s.scheduler == "proportional-fair":
            granted = self.pf(rate_last, rate[:, :, None, :, :])[:, :, 0, :, :, 0]  # [D, C, S, cap]
            # A cell without UEs: the argmax picked column 0, which is not its UE.
            return granted & member[None, :, None, :]
        cells = member[None, :, None, :]  # [1, C, 1, cap]
        if self.s.scheduler == "max-rate":  # per subband, the member with the best rate (the first of equals)
            best = torch.argmax(torch.where(cells, rate, -1.0), dim=3)  # [D, C, S]
            pick = torch.arange(member.shape[1], device=self.device) == best[..., None]
            return pick & cells  # (a cell without members grants nothing)
        # round-robin: one UE per slot, the cell's members in turn
        rank = torch.cumsum(member.to(torch.int64), dim=1) - 1  # [C, cap]: place among the cell's members
        count = torch.clamp(member.sum(dim=1), min=1)  # [C]
        turn = (first_slot + torch.arange(d, device=self.device))[:, None] % count[None, :]  # [D, C]
        pick = member[None] & (rank[None] == turn[..., None])  # [D, C, cap]
        return pick[:, :, None, :].expand(d, member.shape[0], n_sub, member.shape[1])
