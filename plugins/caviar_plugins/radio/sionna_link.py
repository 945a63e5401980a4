"""Communications module: Sionna RT ray tracing in the loop.

Every step it places all UAVs (receivers and metal bodies) at their latest
positions, ray traces them in one solver call and publishes, per UAV:

* ``communications.throughput`` — paper schema ``{UE_type, UE_Id, throughput}`` in
  Mbit/s, for the beam pair chosen by the AI module (latest message on
  ``ai.beam.selection`` ``{"UE_Id": …, "beam_pair": i}``), else for the best pair;
* ``communications.link`` — LOS flag, best and used pair, path gain, SNR, paths;
* ``communications.channel.<UE_Id>`` — H (N_rx_ant × N_tx_ant, complex64), binary;
* ``communications.beam_gains.<UE_Id>`` — gains of all pairs (C_rx × C_tx, float32), binary;
* ``communications.paths.<UE_Id>`` — with ``publish_paths``, the paths (coefficients,
  delays, angles, interactions; :class:`~caviar_plugins.radio.path_data.PathData`), binary;

and then ``communications.state`` ``"Ready"``. Beam pair index = rx_beam · 64 + tx_beam.
Radio materials a ``scene-fitter`` learned (``twin.materials``) apply from the step they
arrive in.
"""

from __future__ import annotations

import dataclasses
from importlib import metadata

import numpy as np

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.radio.link_budget import LinkBudget
from caviar_plugins.radio.link_level import LinkLevel
from caviar_plugins.radio.link_report import LINK_TOPICS, link_messages
from caviar_plugins.radio.link_settings import LinkSettings, check_nr_carrier
from caviar_plugins.radio.prediction import Forecaster, prediction_payload
from caviar_plugins.radio.scene import LookaheadTracer, RadioConfig, RadioScene, check_lookahead_steps, radio_config
from caviar_plugins.rt.scene import scene_path
from caviar_plugins.schema import (
    BEAM_SELECTION,
    FORECAST,
    MATERIALS,
    PATHS,
    POSITIONS,
    PREDICTION,
    STATE,
    every_ue,
    per_ue,
    read_position,
)


@dataclasses.dataclass
class LinkBudgetParams:
    """The link budget and channel publishing both ray-traced links (``sionna-link``,
    ``sionna-traffic-link``) share."""

    bandwidth_hz: float = 40e6
    tx_power_w: float = 0.5
    interference_dbw: float = -130.0
    publish_channels: bool = True
    """Publish H and the beam gains as binary payloads."""


@dataclasses.dataclass
class SionnaLinkParams(LinkBudgetParams, RadioConfig):
    publish_paths: bool = False
    """Publish every UE's paths each step on ``communications.paths.<UE_Id>``: per path the
    coefficient at the array centres, delay, angles of departure and arrival, interaction
    types and points (:class:`~caviar_plugins.radio.path_data.PathData`), what
    ``caviar-core export deepmimo`` turns into a DeepMIMO scenario. Needs a single
    polarization ('V' or 'H')."""
    protocol: str = "physical"
    """``physical``: H with path loss, the link budget above, the Kronecker codebook at
    ``spacing``. ``paper``: the 2023 code's link (docs/paper-protocol.md): LOS path
    dropped, unit-energy H, no refraction or diffuse reflection, 5.714 λ spacing, the
    flat 64-point DFT, Rx 8.23 m below the UAV, R = 40 MHz · log2(1 + |g|²/3248.11).
    It sets those fields (:data:`caviar_plugins.protocol.PAPER_LINK`) and refuses a configuration that sets one
    of them to another value."""
    lookahead: bool = False
    """Look-ahead ray tracing (:class:`~caviar_plugins.radio.scene.LookaheadTracer`):
    one solve traces each UE's current position and the next ``lookahead_steps``
    positions of its ``3D.mobility.forecast`` (waypoint-flight's ``forecast_steps``),
    and later steps whose positions are within ``cache_tolerance_m`` of a traced one
    reuse its channel without a solve. With ``uav_mesh`` each traced position has a UAV
    body of its own (see the tracer: the links agree with solving step by step to the
    tolerance tests/test_solve_lookahead.py states, not bit for bit)."""
    lookahead_steps: int | str = "auto"
    """Forecast positions traced per UE and solve (receivers per solve: UEs × (1 + this));
    ``"auto"``: by Dr.Jit backend, many on a GPU, fewer on the CPU
    (:func:`~caviar_plugins.radio.scene.lookahead_depth`)."""
    cache_tolerance_m: float = 0.01
    """A position within this distance of a traced one reuses its channel."""
    link_model: str = "shannon"
    """``shannon``: each UE gets B·log2(1 + SNR) of its used beam pair (the paper's).
    ``sys``: Sionna SYS on that SNR (:mod:`caviar_plugins.radio.link_level`): the UEs
    share the cell's PRBs (proportional fair), outer-loop link adaptation picks the MCS
    for ``bler_target``, PHY abstraction decodes on the NR PDSCH tables, and the
    throughput is the decoded bits; ``communications.link`` adds MCS, TBLER and HARQ."""
    subcarrier_spacing_hz: float = 120e3
    """``sys``: NR numerology (120 kHz: 0.125 ms slots); ``bandwidth_hz // (12·SCS)`` PRBs."""
    harq_processes: int = 8
    """``sys``: slots per Sionna SYS call (see :class:`~caviar_plugins.radio.link_settings.LinkSettings`)."""
    bler_target: float = 0.1
    device: str = "auto"
    """``sys``: the torch device of the link level (``auto``: Sionna's choice, a GPU where
    there is one; ``cpu``, ``cuda``, ``cuda:N``)."""
    predict_horizons_s: list[float] = dataclasses.field(default_factory=list)
    """Seconds ahead at which to predict every UE's link each step (for example
    ``[0.5, 1.0, 2.0]``), on ``communications.prediction``: the forecast positions (the
    UE's ``3D.mobility.forecast``, else constant velocity) traced in the step's solve
    (:mod:`caviar_plugins.radio.prediction`). Needs ``uav_mesh = false``."""

    warm_up_ues: int = 0
    """Trace this many receivers at setup (below the transmitter, 1.5 m up; twice, as the
    shoot cache records on a first solve and compiles on the second), so that the first
    steps do not compile Dr.Jit's kernels: a paced run (``pace`` in
    ``[episode]``) then starts on time. Use the receivers of a step: UEs × (1 + the
    number of ``predict_horizons_s``). 0 (default): no warm-up."""

    def __post_init__(self):
        paper.check_protocol(self.protocol)
        if self.link_model not in ("shannon", "sys"):
            raise ValueError(f"link_model: expected 'shannon' or 'sys', got {self.link_model!r}")
        if self.link_model == "sys":
            if self.protocol == "paper":
                raise ValueError("link_model: 'sys' needs protocol = 'physical' (the paper's rate is its own model)")
            check_nr_carrier(self.frequency_hz, "frequency_hz")
            self.link_settings = LinkSettings(
                num_prb=int(self.bandwidth_hz // (12 * self.subcarrier_spacing_hz)),
                subcarrier_spacing_hz=self.subcarrier_spacing_hz, bler_target=self.bler_target,
                harq_processes=self.harq_processes, device=self.device)
        if self.protocol == "paper":
            caviar.apply_preset(self, paper.PAPER_LINK, "protocol = 'paper'")
        super().__post_init__()
        if not isinstance(self.lookahead, bool):
            raise ValueError(f"lookahead: expected true or false, got {self.lookahead!r}")
        check_lookahead_steps(self.lookahead_steps)
        if not (isinstance(self.cache_tolerance_m, (int, float)) and self.cache_tolerance_m >= 0):
            raise ValueError(f"cache_tolerance_m: expected a distance >= 0 (m), got {self.cache_tolerance_m!r}")
        if self.warm_up_ues < 0:
            raise ValueError(f"warm_up_ues: expected >= 0, got {self.warm_up_ues}")
        _check_publish_paths(self)
        if self.warm_up_ues and self.uav_mesh:
            raise ValueError("warm_up_ues needs uav_mesh = false (a warm-up receiver would take a UAV body "
                             "along, and adding bodies later recompiles the kernels anyway)")
        for i, h in enumerate(self.predict_horizons_s):
            if not (isinstance(h, (int, float)) and np.isfinite(h) and h > 0):
                raise ValueError(f"predict_horizons_s.{i}: expected a positive number of seconds, got {h!r}")
        if self.predict_horizons_s and self.uav_mesh:
            raise ValueError("predict_horizons_s needs uav_mesh = false (a solve places each UAV body at one "
                             "position; predicted positions would see the bodies where the UAVs are now)")


class SionnaLink(caviar.Plugin):
    subscribe = [POSITIONS, BEAM_SELECTION, FORECAST, MATERIALS]
    # (without them: the best pair, no look-ahead, the scene's own materials)
    optional = (BEAM_SELECTION, FORECAST, MATERIALS)
    publishes = (*LINK_TOPICS, STATE, PREDICTION, every_ue(PATHS), caviar.STATUS_TOPIC)
    Params = SionnaLinkParams

    def setup(self, ctx):
        p = ctx.params
        self.p = p
        self.radio = RadioScene(radio_config(p), seed=ctx.seed, base_dir=ctx.config_dir)
        self.radio.keep_paths = p.publish_paths
        self.path_settings = _path_settings(p, ctx) if p.publish_paths else {}
        self.budget = LinkBudget(bandwidth_hz=p.bandwidth_hz, tx_power_w=p.tx_power_w,
                                 interference_dbw=p.interference_dbw)
        self.ue_type: dict[str, str] = {}
        self.positions: dict[str, np.ndarray] = {}
        self.selected: dict[str, int] = {}
        self.forecast: dict[str, list[np.ndarray]] = {}
        self.forecaster = Forecaster(p.predict_horizons_s) if p.predict_horizons_s else None
        if p.warm_up_ues:  # the kernels compile now, before the run's clock starts
            foot = np.array([p.tx_position[0], p.tx_position[1], 1.5])
            warm = {f"warm-up-{i}": foot + [i, 0.0, 0.0] for i in range(p.warm_up_ues)}
            for moved in (0.0, 1.0):  # the shoot cache records on the first solve, compiles on the second
                self.radio.place({k: q + moved for k, q in warm.items()})
                self.radio.solve()
            self.radio.remove(warm)
        self.lookahead = LookaheadTracer(self.radio, p.lookahead_steps, p.cache_tolerance_m) if p.lookahead else None
        self.link_level = None
        if p.link_model == "sys":
            self.link_level = LinkLevel(p.link_settings, n_cell=1, seed=ctx.seed)
            self.slots = max(1, round(ctx.ts * ctx.every / p.link_settings.slot_s))
            if self.slots % p.harq_processes:
                raise caviar.ConfigError(f"a step is {self.slots} slots, not whole groups of harq_processes = "
                                         f"{p.harq_processes}", "params.harq_processes")
            self.columns: dict[str, int] = {}

    def step(self, t, inbox):
        self._read(t, inbox)
        if not self.positions:
            return
        ahead = {ue: self.forecaster.ahead(ue, t) for ue in self.positions} if self.forecaster else {}
        links = self._solve(ahead)
        for ue, rows in ahead.items():
            yield PREDICTION, prediction_payload(self.ue_type[ue], ue, t, rows,
                                                 [links.pop(_predicted(ue, i)) for i in range(len(rows))], self._mbps)
        n_pairs = self.radio.w_rx.shape[1] * self.radio.n_tx_beams
        decoded = self._decode(links, n_pairs) if self.link_level is not None else {}
        for ue, link in links.items():
            mbps, extra = decoded.get(ue, (None, None))
            yield from link_messages(self.ue_type[ue], ue, link, self.selected.get(ue), n_pairs, self._mbps,
                                     self._snr, self.p.publish_channels, extra, throughput_mbps=mbps)
            if self.p.publish_paths and link.paths is not None:
                yield per_ue(PATHS, ue), dataclasses.replace(link.paths, settings=self.path_settings).to_bytes()
        yield STATE, "Ready"
        status = self.radio.cache_status()
        if status is not None:
            yield caviar.STATUS_TOPIC, status

    def _read(self, t: float, inbox) -> None:
        for m in inbox:
            if m.topic == POSITIONS:
                self.ue_type[m.data["UE_Id"]] = m.data["UE_type"]
                self.positions[m.data["UE_Id"]] = read_position(m.data)
                if self.forecaster is not None:  # when the position was measured: now, less its age
                    v = m.data.get("velocity")
                    self.forecaster.observe(m.data["UE_Id"], _time(m, t) - float(m.data.get("age_s", 0.0)),
                                            self.positions[m.data["UE_Id"]],
                                            None if v is None else read_position({"position": v}))
            elif m.topic == MATERIALS:  # a scene-fitter's learned materials, from this step's solve on
                self.radio.set_materials(m.data["materials"])
            elif m.topic == BEAM_SELECTION:
                self.selected[m.data["UE_Id"]] = int(m.data["beam_pair"])
            elif m.topic == FORECAST:
                self.forecast[m.data["UE_Id"]] = [read_position({"position": q}) for q in m.data["positions"]]
                if self.forecaster is not None:
                    self.forecaster.plan(m.data["UE_Id"], _time(m, t), self.forecast[m.data["UE_Id"]],
                                         float(m.data["ts"]))

    def _solve(self, ahead: dict[str, list]) -> dict:
        """Every UE's link now, and at its predicted positions (keys ``UE#hI``, the I-th
        horizon; look-ahead's are ``UE@K``) in the same solve, or in one of their own next
        to look-ahead's."""
        predicted = {_predicted(ue, i): p for ue, rows in ahead.items() for i, (_, _, p) in enumerate(rows)}
        if self.lookahead is None:
            self.radio.place({**self.positions, **predicted})
            return self.radio.solve()
        links = self.lookahead.links(self.positions, self.forecast)
        if predicted:
            self.radio.place(predicted)
            links = {**links, **self.radio.solve()}
        return links

    def _decode(self, links, n_pairs: int) -> dict[str, tuple[float, dict]]:
        """``sys``: the step's slots through Sionna SYS for every UE on the SNR of its used
        pair; per UE its throughput (Mbit/s of decoded bits) and link-level details."""
        for ue in links:
            self.columns.setdefault(ue, len(self.columns))
        snr_db = np.full(len(self.columns), np.nan)
        serving = np.full(len(self.columns), -1)
        for ue, link in links.items():
            pair = self.selected.get(ue, link.best_pair)
            pair = pair if 0 <= pair < n_pairs else link.best_pair  # link_messages reports a bad pair
            snr_db[self.columns[ue]] = 10 * np.log10(max(self._snr(float(link.gains.flat[pair])), 1e-30))
            serving[self.columns[ue]] = 0
        assert self.link_level is not None
        res = self.link_level.run(np.tile(snr_db, (self.slots, 1)), serving)
        bps = res.throughput_bps(self.slots, self.p.link_settings.slot_s)
        return {ue: (round(float(bps[c]) / 1e6, 6), {"link_model": "sys", **res.summary(c)})
                for ue, c in self.columns.items() if ue in links}

    def _snr(self, gain: float) -> float:
        if self.p.protocol == "paper":
            return gain / paper.PAPER_SNR_DIVISOR
        return float(self.budget.sinr(gain))

    def _mbps(self, gain: float) -> float:
        if self.p.protocol == "paper":
            return float(paper.paper_rate_mbps(gain))
        return float(self.budget.throughput_mbps(gain))

    def state(self):
        # The scene, budget and solver come from setup; what the UEs did, the forecasts,
        # the look-ahead's traces, the link level's loops and the scene's receivers are the state.
        return {"ue_type": self.ue_type, "positions": self.positions, "selected": self.selected,
                "forecast": self.forecast, "forecaster": self.forecaster, "scene": self.radio.snapshot(),
                "lookahead": None if self.lookahead is None else self.lookahead.state(),
                "link_level": None if self.link_level is None else self.link_level.state(),
                "columns": getattr(self, "columns", None)}

    def restore(self, state):
        self.ue_type, self.positions, self.selected = state["ue_type"], state["positions"], state["selected"]
        self.forecast, self.forecaster = state["forecast"], state["forecaster"]
        self.radio.restore(state["scene"])
        if self.lookahead is not None:
            self.lookahead.restore(state["lookahead"])
        if self.link_level is not None:
            self.link_level.restore(state["link_level"])
            self.columns = state["columns"]


def _check_publish_paths(p: SionnaLinkParams) -> None:
    if p.publish_paths and p.polarization not in ("V", "H"):
        raise ValueError(f"publish_paths needs polarization = 'V' or 'H' (one coefficient per path), "
                         f"got {p.polarization!r}")


def _path_settings(p: SionnaLinkParams, ctx) -> dict:
    """What an exporter of the paths needs to know of the link: its ray-tracing settings,
    the scene's file (None: free space), the bandwidth and the versions."""
    scene = scene_path(p.scene, ctx.config_dir)
    link = dataclasses.asdict(radio_config(p))
    rays = link.pop("raytracing")  # (flat beside the link's own settings, as exporters read them)
    return {**link, **rays, "scene_file": None if scene is None else str(scene.resolve()),
            "bandwidth_hz": p.bandwidth_hz, "protocol": p.protocol, "module": ctx.name, "plugin": "sionna-link",
            "sionna_rt": metadata.version("sionna-rt")}


def _time(message, t: float) -> float:
    """When ``message`` was published (its step's time), or now."""
    return t if message.time is None else float(message.time)


def _predicted(ue: str, i: int) -> str:
    """The receiver of ``ue``'s position at its i-th prediction horizon."""
    return f"{ue}#h{i}"
