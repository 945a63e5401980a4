"""``radio-network``'s parameters, :class:`NetworkParams` (settings only, checked before
anything runs), and the factories of what they describe: :func:`plan` (the cells, their
codebooks, the link level's settings) and :func:`make_channel` (the channel model)."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, ClassVar, Sequence

import numpy as np

from caviar_plugins import limits
from caviar_plugins.network.beams import BeamSettings
from caviar_plugins.network.cells import Cell, Column
from caviar_plugins.network.channel import Channel
from caviar_plugins.network.deployment import carrier_key, deployment, nr_prbs
from caviar_plugins.network.free_space import FreeSpaceChannel
from caviar_plugins.network.handover import HandoverSettings
from caviar_plugins.network.layout import LayoutSettings, Wraparound
from caviar_plugins.network.radio_map import RadioMapSettings
from caviar_plugins.network.raytraced import NETWORK_RAYS, Evolution
from caviar_plugins.network.tr38901 import CHANNELS as STOCHASTIC
from caviar_plugins.network.tr38901 import StochasticSettings, Tr38901Channel
from caviar_plugins.network.traced_channel import RayTracedChannel
from caviar_plugins.network.traffic import TrafficSettings
from caviar_plugins.network.uplink import UplinkSettings
from caviar_plugins.radio.link_settings import LinkSettings, check_nr_carrier
from caviar_plugins.rt.settings import TraceSettings

INTERFERENCE = ("full-buffer", "scheduled")
CHANNELS = ("free-space", "ray-traced", *STOCHASTIC)


UE_REPORTS = ("per-ue", "table")
"""``ue_reports``' choices: a ``network.ue`` message a UE, or one ``network.ues`` table a step."""


@dataclasses.dataclass
class NetworkParams:
    """``radio-network``'s parameters (``[modules.NAME.params]``)."""

    sites: list[dict] = dataclasses.field(default_factory=list)
    carrier_hz: float = 3.5e9
    bandwidth_hz: float = 20e6
    subcarrier_spacing_hz: float = 30e3
    num_prb: int | None = None
    tx_power_dbm: float = 43.0
    array: list[int] = dataclasses.field(default_factory=lambda: [4, 4])
    noise_figure_db: float = 7.0
    link_model: str = "sys"
    scheduler: str = "proportional-fair"
    interference: str = "full-buffer"
    bler_target: float = 0.1
    mcs_table: int = 1
    harq_processes: int = 1
    """Slots computed together, one per HARQ process (see
    :class:`~caviar_plugins.radio.link_settings.LinkSettings`): 8 is about 5x faster."""
    compile: bool = False
    """``torch.compile`` the link level (Sionna SYS): about 4x faster a step, after
    about 20 s of compilation at the first step (see
    :class:`~caviar_plugins.radio.link_settings.LinkSettings`); the uplink's powers and SINRs,
    and with beams the downlink's per-slot SINRs, each as one compiled program too, both as one
    with beams and the uplink (the same numbers to float64's rounding, the powers to float32's;
    on a GPU a few kernels a step instead of about 100 launches)."""
    groups_per_call: int = 1
    """With ``compile`` and full buffers, groups of slots run as one compiled call, a loop compiled
    once whatever its length: 25 make a 0.1 s step of 8-slot groups one call instead of 25, each
    costing the host about 0.2-0.4 ms (see :class:`~caviar_plugins.radio.link_settings.LinkSettings`)."""
    cuda_graphs: bool | None = None
    """With ``compile``, replay each compiled group of slots as a CUDA graph (None: on a CUDA
    device, off elsewhere; see :class:`~caviar_plugins.radio.link_settings.LinkSettings`)."""
    device: str = "auto"
    """The torch device of the link level (Sionna SYS): ``auto`` (Sionna's choice, a GPU
    where there is one), ``cpu``, ``cuda`` or ``cuda:N``."""
    subbands: int = 8
    """Frequencies at which the ray-traced channel is evaluated, one per group of
    adjacent PRBs: the scheduler's unit and the EESM's inputs. The free-space channel
    is flat (one)."""
    handover: HandoverSettings = dataclasses.field(default_factory=HandoverSettings)
    """A3 handover and cell selection: ``offset_db``, ``hysteresis_db``,
    ``time_to_trigger_s``... (see :class:`~caviar_plugins.network.handover.HandoverSettings`)."""
    antenna_height_m: float = 1.5
    """A UE's antenna above the position it reports (SUMO reports the street)."""
    channel: str = "free-space"
    """``free-space`` (Friis along the straight line), ``ray-traced`` (Sionna RT, every
    site in one solve, refreshed every ``evolution.refresh_s``) or TR 38.901's
    stochastic ``38.901-uma``, ``38.901-umi``, ``38.901-rma`` (Sionna's models: pathloss,
    LOS probability, shadow fading, O2I; no fast fading; see ``tr38901``)."""
    layout: LayoutSettings | None = None
    """A standard hexagonal deployment instead of hand-placed ``sites``: ``rings``,
    ``isd_m``, ``height_m``, ``wraparound``, and UEs dropped per sector
    (``ues_per_sector``...; see :class:`~caviar_plugins.network.layout.LayoutSettings`)."""
    column: Column | None = None
    """The elements behind each port: a vertical column with an electrical tilt (TR
    38.901 Table 7.8-1: ``{ elements = 10, spacing_wavelengths = 0.5,
    electrical_tilt_deg = 12 }``), part of every cell's pattern (see
    :class:`~caviar_plugins.network.cells.Column`)."""
    tr38901: StochasticSettings = dataclasses.field(default_factory=StochasticSettings)
    """The 38.901 channel's O2I building mix, shadow fading and redraw distance (see
    :class:`~caviar_plugins.network.tr38901.StochasticSettings`)."""
    report_cells: int = 0
    """``network.ue`` lists the RSRP of this many strongest cells (0: every cell), as a
    measurement report lists the serving cell and its best neighbours."""
    ue_reports: str = "per-ue"
    """How the UEs' reports are published each step: ``"per-ue"``, a ``network.ue`` message a UE
    (as ``communications.throughput``), or ``"table"``, one ``network.ues`` message a step holding
    the same fields as columns, a row a UE (:func:`~caviar_plugins.network.ues.ue_table`; at 1,000 UEs
    on a 2-core CPU the step's host work fell from 18-22 to 13-16 ms and the host's encoding of its
    messages from 17 to 3.5 ms; at 100 UEs the table costs as much as the messages).
    ``communications.throughput`` stays a message a UE either way (the paper's schema, what
    other modules read)."""
    scene: str = "empty"
    """The ray tracer's scene (the ray-traced channel, the radio map, the layout's drops
    outdoors): a shipped one, a Mitsuba XML file (``scene build``'s), or ``empty``."""
    raytracing: TraceSettings = dataclasses.field(default_factory=lambda: NETWORK_RAYS)
    """How the ray-traced channel traces (:class:`~caviar_plugins.rt.settings.TraceSettings`):
    here 1e5 rays per site to depth 3, line of sight, specular reflection and diffraction."""
    evolution: Evolution = dataclasses.field(default_factory=Evolution)
    """The ray-traced channel between traces: ``refresh_s``, ``mode`` (``doppler`` or
    ``hold``), ``paths_per_link`` (see :class:`~caviar_plugins.network.raytraced.Evolution`)."""
    beams: BeamSettings | None = None
    """SSB beams from the channel (a table turns them on): every cell sweeps a DFT
    codebook of ``horizontal × vertical`` beams on its panel, L1-RSRP is the best beam's,
    data goes on the serving cell's best beam, and in each slot every other cell
    interferes with its beam toward the UE it schedules then, on the victim's channel
    (:mod:`~caviar_plugins.network.beams`). Needs the free-space or ray-traced channel."""
    uplink: UplinkSettings | None = None
    """The uplink (a table turns it on): PUSCH with open-loop power control (``p0_dbm``,
    ``alpha``, ``ue_max_power_dbm``), interference from the UEs other cells schedule in the
    slot, Sionna SYS on the PUSCH tables (:mod:`~caviar_plugins.network.uplink`);
    ``network.ue`` adds ``ul_*``."""
    traffic: TrafficSettings | None = None
    """The load (a table turns it on; without it, full buffer): per direction each UE's
    ``full-buffer``, ``ftp3`` (``ftp = { file_bytes, arrival_rate_hz }``) or ``none``, and
    the twin's messages it carries (``carry = [{ topic, direction, deliver_to }]``); the
    scheduler serves queued bytes only, and each completed transfer goes on
    ``network.transfers`` (:mod:`~caviar_plugins.network.traffic`)."""
    radio_map: RadioMapSettings | None = None
    """A best-server SINR map of ``scene`` at setup (a table turns it on):
    ``cell_size_m``, ``height_m``, ``margin_m``, its own ``raytracing`` (see
    :class:`~caviar_plugins.network.radio_map.RadioMapSettings`); written to
    ``radio-map.npz`` and ``radio-map.png`` and announced on ``network.radio_map``."""

    allow_large: bool = False
    """Lift the bounds on the UEs a layout drops, the FTP arrival rate, the panel's elements,
    the rays traced and the radio map's cells (:mod:`caviar_plugins.limits`), for a machine
    that can do more."""

    moved: ClassVar[dict[str, str]] = {"raytracing.scene": "scene", "raytracing.refresh_s": "evolution.refresh_s",
                                       "raytracing.evolve": "evolution.mode",
                                       "raytracing.paths_per_link": "evolution.paths_per_link"}

    def __post_init__(self):
        if self.channel not in CHANNELS:
            raise ValueError(f"channel: expected one of {list(CHANNELS)}, got {self.channel!r}")
        if self.ue_reports not in UE_REPORTS:
            raise ValueError(f"ue_reports: expected one of {list(UE_REPORTS)}, got {self.ue_reports!r}")
        if isinstance(self.report_cells, bool) or self.report_cells < 0:
            raise ValueError(f"report_cells: expected a number of cells >= 0, got {self.report_cells!r}")
        if self.beams is not None and self.channel not in ("free-space", "ray-traced"):
            raise ValueError(f"beams: need the channel's path directions, which the free-space and "
                             f"ray-traced channels have; got channel = {self.channel!r}")
        for key in ("carrier_hz", "bandwidth_hz", "subcarrier_spacing_hz"):  # (every cell's, unless a site's)
            if not getattr(self, key) > 0:
                raise ValueError(f"{key}: expected a positive number of Hz, got {getattr(self, key)!r}")
        if self.interference not in INTERFERENCE:
            raise ValueError(f"interference: expected one of {list(INTERFERENCE)}, got {self.interference!r}")
        if self.num_prb is None:
            self.num_prb = nr_prbs(self.bandwidth_hz, self.subcarrier_spacing_hz)
            if self.num_prb is None:
                raise ValueError(f"num_prb: {self.bandwidth_hz:g} Hz at {self.subcarrier_spacing_hz:g} Hz "
                                 f"spacing is not an NR channel bandwidth; give num_prb")
        if self.num_prb * 12 * self.subcarrier_spacing_hz > self.bandwidth_hz:
            raise ValueError(f"num_prb: {self.num_prb} PRBs of {12 * self.subcarrier_spacing_hz:g} Hz do not "
                             f"fit in bandwidth_hz = {self.bandwidth_hz:g}")
        made = plan(self)  # (the cells, codebooks and link level it makes are checked now, before anything runs)
        check_bounds(self, made.cells)


def check_bounds(p: NetworkParams, cells: Sequence[Cell]) -> None:
    """The work and memory the settings ask for, against :mod:`caviar_plugins.limits`
    (``allow_large`` lifts them)."""
    allow = p.allow_large
    if p.layout is not None and p.layout.ues_per_sector:
        limits.bounded("layout.ues_per_sector", p.layout.ues_per_sector * len(cells), limits.DROPPED_UES,
                       f"{p.layout.ues_per_sector:,} UEs in each of {len(cells)} sectors", allow, "UEs")
    if p.traffic is not None:
        limits.bounded("traffic.ftp.arrival_rate_hz", p.traffic.ftp.arrival_rate_hz, limits.FTP_ARRIVAL_RATE_HZ,
                       "the FTP arrival rate per UE", allow, "files a second")
    tables_of = {s.get("name"): (i, s) for i, s in enumerate(p.sites)}  # (hand-placed sites)
    for c in cells:
        i, site = tables_of.get(c.site, (0, {}))
        limits.bounded(f"sites.{i}.array" if "array" in site else "array", c.array[0] * c.array[1],
                       limits.ARRAY_ELEMENTS, f"cell {c.name}'s panel of {c.array[0]} × {c.array[1]}", allow,
                       "elements")
    if p.radio_map is not None and cells:
        m = p.radio_map
        xy = np.array([c.position[:2] for c in cells])
        nx, ny = np.ceil((xy.max(axis=0) - xy.min(axis=0) + 2 * m.margin_m) / m.cell_size_m)
        limits.bounded("radio_map.cell_size_m", float(nx * ny), limits.MAP_CELLS,
                       f"a map of {nx:,.0f} × {ny:,.0f} cells of {m.cell_size_m:g} m", allow, "cells")
    tables = [("raytracing", p.raytracing)] if p.channel == "ray-traced" else []
    if p.radio_map is not None:
        tables.append(("radio_map.raytracing", p.radio_map.raytracing))
    for key, rays in tables:
        limits.bounded(f"{key}.samples_per_src", rays.samples_per_src, limits.SAMPLES_PER_SOURCE,
                       "the rays traced from each source", allow, "rays")


@dataclasses.dataclass(frozen=True)
class NetworkPlan:
    """What a network's settings make (:func:`plan`): its cells, their SSB codebooks (None
    without ``beams``) and the link level's settings."""

    cells: list[Cell]
    codebooks: list[Any] | None
    link: LinkSettings


def plan(p: NetworkParams) -> NetworkPlan:
    """The objects :class:`NetworkParams` describe, built from the settings (which hold
    nothing else): the cells of the sites or the layout, each checked as an NR carrier, their
    codebooks, and the link level's settings (one subband where the channel is flat)."""
    cells: list[Cell] = deployment(p)
    for c in cells:
        check_nr_carrier(c.carrier_hz, carrier_key(p, c))
    codebooks = None if p.beams is None else [p.beams.codebook(c.array) for c in cells]
    flat = p.channel != "ray-traced" or p.evolution.mode == "hold"
    assert p.num_prb is not None  # (set by NetworkParams)
    link = LinkSettings(num_prb=p.num_prb, subcarrier_spacing_hz=p.subcarrier_spacing_hz, bler_target=p.bler_target,
                        mcs_table=p.mcs_table, scheduler=p.scheduler, link_model=p.link_model,
                        harq_processes=p.harq_processes, subbands=1 if flat else p.subbands, compile=p.compile,
                        groups_per_call=p.groups_per_call, cuda_graphs=p.cuda_graphs, device=p.device)
    return NetworkPlan(cells, codebooks, link)


def make_channel(kind: str, params: Any, cells: Sequence[Cell], *, link: Any, device: Any, seed: int,
                 base_dir: pathlib.Path | None = None) -> Channel:
    """The channel model ``kind`` of a network's ``params``
    (:class:`~caviar_plugins.network.settings.NetworkParams`) over ``cells``: ``link`` is its
    :class:`~caviar_plugins.radio.link_settings.LinkSettings` (the subbands a frequency-selective
    channel is evaluated at), ``device`` the resolved torch device, ``seed`` the run's."""
    if kind == "free-space":
        return FreeSpaceChannel(cells)
    if kind == "ray-traced":
        return RayTracedChannel(params, cells, link=link, device=device, seed=seed, base_dir=base_dir)
    if kind in STOCHASTIC:
        layout = params.layout
        wrap = Wraparound(layout) if layout is not None and layout.wraparound else None
        return Tr38901Channel(kind, STOCHASTIC[kind], list(cells), params.tr38901, wrap, device=device, seed=seed)
    raise ValueError(f"channel: no model named {kind!r}")
