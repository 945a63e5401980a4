"""The link level's settings (:class:`LinkSettings`: numerology, MCS tables, scheduler, link
model, HARQ processes, subbands, compile and device), checked when made, and the NR facts they
are checked against; :mod:`caviar_plugins.radio.link_level` runs them."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from caviar_plugins.torch_device import check_setting, is_cuda

NUMEROLOGIES = (15e3, 30e3, 60e3, 120e3)
NR_RANGES_HZ = ((410e6, 7.125e9), (24.25e9, 71e9))
"""NR frequency ranges (FR1, FR2), where the BLER tables (NR LDPC, NR MCS tables) apply."""


def check_nr_carrier(carrier_hz: float, key: str) -> None:
    """ValueError naming ``key`` for a carrier outside the NR bands."""
    if not any(lo <= carrier_hz <= hi for lo, hi in NR_RANGES_HZ):
        raise ValueError(f"{key}: {carrier_hz:g} Hz is outside the NR bands the BLER tables are for "
                         f"(FR1 0.41-7.125 GHz, FR2 24.25-71 GHz)")


SCHEDULERS = ("proportional-fair", "round-robin", "max-rate")
LINK_MODELS = ("sys", "shannon")
DATA_SYMBOLS_PER_SLOT = 12  # of 14: two for control and reference signals
PDSCH = 1  # Sionna's MCS category of the downlink (0: PUSCH); its BLER tables are PDSCH_table*.json
PUSCH = 0  # the uplink's: PUSCH_table1.json and PUSCH_table2.json
DIRECTIONS = {"downlink": PDSCH, "uplink": PUSCH}


@dataclasses.dataclass(frozen=True)
class LinkSettings:
    """A link level's settings (:class:`~caviar_plugins.radio.link_level.LinkLevel`), checked when made."""

    num_prb: int
    subcarrier_spacing_hz: float = 30e3
    bler_target: float = 0.1
    mcs_table: int = 1
    scheduler: str = "proportional-fair"
    link_model: str = "sys"
    harq_processes: int = 1
    """Slots computed together: slot k belongs to HARQ process k mod D, which keeps its own
    link-adaptation loop and proportional-fair history and learns its last transmission's
    outcome before its next one, D slots later (NR's interleaved HARQ processes). 1 (the
    default): every slot sees the previous one's outcome. Larger D: D times fewer calls."""
    subbands: int = 1
    """Groups of adjacent PRBs (as equal as ``num_prb`` allows) with one SINR each, the
    unit the scheduler allocates: 1 is a wideband (flat) channel."""
    compile: bool = False
    """Run each group of slots (scheduler, CSI, link adaptation, EESM and PHY abstraction)
    as one ``torch.compile`` program, compiled once per process and UE capacity (about 20 s
    on a 2-core CPU). 21 cells × 100 UEs, 8 subbands, 200 slots: 0.17 s eager, 0.044 s
    compiled on a 2-core AMD EPYC, with 17 top-level torch operations a group instead of 646
    (on a GPU, kernel launches). The same MCS, effective SINR and BLER as eager; the HARQ
    outcomes are drawn from the compiled kernels' own random stream (deterministic for a
    seed, not eager's draws). After its first calls at a UE capacity, dynamo checks only the
    guards that tell the compiled entries apart
    (:meth:`~caviar_plugins.radio.link_level.LinkLevel._guards`: half the host's work of picking
    the entry, the same results)."""
    groups_per_call: int = 1
    """With ``compile``, groups of slots (``harq_processes`` slots each) that run as one compiled
    call where every link has a full buffer (with queues, whether a group runs depends on the
    queues the group before left: one a call; groups past the last whole chunk: one a call too).
    Each compiled call costs the host a fixed price (dynamo picking its entry, the program's
    inputs and side effects, inductor's wrapper: about 0.2-0.4 ms at 21 cells × 1,000 UEs on a 2-core
    CPU, 25 calls a 0.1 s step of 8-slot groups). A chunk is one loop over its groups that torch
    compiles once whatever its length (:mod:`~caviar_plugins.radio.link_chunks`; written out
    group after group, until 2026-11-29 the compile grew with them: 237 s for 25 at 1,000 UEs on a
    2-core AMD EPYC), so 25 make such a step one call, compiled in about the time of one group. A
    call's slots are tallied in its own program. The same results as 1, bit for bit (with
    ``cuda_graphs``, a chunk is no graph: its loop runs on the host)."""
    cuda_graphs: bool | None = None
    """With ``compile``, capture the compiled group of slots as a CUDA graph
    (``torch.compile(mode="reduce-overhead")``): one graph launch a group instead of its
    kernels, its outputs copied out before the next replay overwrites them. None (the
    default): on a CUDA device, off elsewhere (:func:`cuda_graphs_on`); True on a CPU compiles in
    that mode all the same (torch skips the graphs there: the same numbers). On the H200
    (2026-11-28) the captured group failed at its second replay: Sionna's link adaptation (OLLA)
    keeps its offset, an output of the last replay, and reads it in the next ("accessing tensor
    output of CUDAGraphs that has been overwritten"), so it was off until the night of
    2026-11-29; that state is now copied out after each replay (tested on the CPU), and where
    torch still refuses a replay the link level goes on compiled without graphs, with a warning
    (tested on the CPU with that error). ``scripts/gpu_check.py`` measures the graphs at the
    next GPU run (``network_21x100_cuda_graphs``). A chunk of groups (``groups_per_call``) is no
    graph: its loop runs on the host."""
    device: str = "auto"
    """The torch device of the Sionna SYS blocks and every tensor they are given: ``auto``
    (Sionna's choice, a GPU where there is one), ``cpu``, ``cuda`` or ``cuda:N``. numpy
    enters and leaves only at the call's boundary (:mod:`caviar_plugins.torch_device`)."""
    direction: str = "downlink"
    """``downlink`` (PDSCH: MCS tables 1-4 and their BLER tables) or ``uplink`` (PUSCH: MCS
    tables 1-2, Sionna's PUSCH BLER tables)."""

    @property
    def mcs_category(self) -> int:
        return DIRECTIONS[self.direction]

    def __post_init__(self):
        check_setting(self.device)
        if self.num_prb < 1:
            raise ValueError(f"num_prb: expected at least 1 PRB, got {self.num_prb}")
        if not 0.0 < self.bler_target < 1.0:
            raise ValueError(f"bler_target: expected a BLER target in (0, 1), got {self.bler_target}")
        if self.direction not in DIRECTIONS:
            raise ValueError(f"direction: expected 'downlink' or 'uplink', got {self.direction!r}")
        if self.direction == "downlink" and self.mcs_table not in (1, 2, 3, 4):
            raise ValueError(f"mcs_table: expected an NR PDSCH MCS table index 1-4, got {self.mcs_table}")
        if self.direction == "uplink" and self.mcs_table not in (1, 2):
            raise ValueError(f"mcs_table: expected an NR PUSCH MCS table index 1-2, got {self.mcs_table}")
        if self.scheduler not in SCHEDULERS:
            raise ValueError(f"scheduler: expected one of {list(SCHEDULERS)}, got {self.scheduler!r}")
        if self.link_model not in LINK_MODELS:
            raise ValueError(f"link_model: expected one of {list(LINK_MODELS)}, got {self.link_model!r}")
        if not 1 <= self.harq_processes <= 16:
            raise ValueError(f"harq_processes: expected 1 to 16 (NR's HARQ processes), got {self.harq_processes}")
        if not 1 <= self.subbands <= self.num_prb:
            raise ValueError(f"subbands: expected 1 to num_prb = {self.num_prb}, got {self.subbands}")
        self._check_cuda_graphs()
        self._check_groups_per_call()
        if self.subcarrier_spacing_hz not in NUMEROLOGIES:
            raise ValueError(f"subcarrier_spacing_hz: expected an NR numerology {sorted(NUMEROLOGIES)}, "
                             f"got {self.subcarrier_spacing_hz:g}")

    def _check_groups_per_call(self) -> None:
        if not 1 <= self.groups_per_call <= 64:
            raise ValueError(f"groups_per_call: expected 1 to 64 groups of slots a call, got {self.groups_per_call}")
        if self.groups_per_call > 1 and not self.compile:
            raise ValueError("groups_per_call: runs groups of slots as one compiled call; it needs compile = true")

    def _check_cuda_graphs(self) -> None:
        if self.cuda_graphs not in (None, True, False):
            raise ValueError(f"cuda_graphs: expected true, false or none (off), "
                             f"got {self.cuda_graphs!r}")
        if self.cuda_graphs and not self.compile:
            raise ValueError("cuda_graphs: captures the compiled group of slots; it needs compile = true")

    @property
    def slot_s(self) -> float:
        """NR slot: 14 symbols, 1 ms at 15 kHz, halved with each doubling of the spacing."""
        return 1e-3 * 15e3 / self.subcarrier_spacing_hz

    @property
    def prb_bandwidth_hz(self) -> float:
        return 12 * self.subcarrier_spacing_hz

    @property
    def subband_prbs(self) -> np.ndarray:
        """[subbands]: PRBs in each subband (they differ by at most one)."""
        return np.array([len(a) for a in np.array_split(np.arange(self.num_prb), self.subbands)])

    @property
    def subband_frequencies_hz(self) -> np.ndarray:
        """[subbands]: each subband's centre, as an offset from the carrier (Hz)."""
        prb_centres = (np.arange(self.num_prb) + 0.5 - self.num_prb / 2) * self.prb_bandwidth_hz
        return np.array([a.mean() for a in np.array_split(prb_centres, self.subbands)])


def cuda_graphs_on(settings: LinkSettings, device: Any) -> bool:
    """Whether a link level of ``settings`` on the torch ``device`` captures its compiled
    group of slots as a CUDA graph: as ``cuda_graphs`` says (None, the default: on a CUDA device,
    compiled; see :attr:`LinkSettings.cuda_graphs`)."""
    if not settings.compile or settings.link_model != "sys":
        return False
    if settings.cuda_graphs is None:
        return is_cuda(device)
    return bool(settings.cuda_graphs)
