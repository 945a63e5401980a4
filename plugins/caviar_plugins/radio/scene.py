"""Ray-traced MIMO links with Sionna RT: the scene is loaded once and kept in memory;
between steps only receivers and UAV meshes move.

This module knows nothing of caviar: :class:`RadioScene` is what the communications
plugin and the benchmarks call. It is a client of :mod:`caviar_plugins.rt`: the scene and
its moving objects (:mod:`~caviar_plugins.rt.scene`), and the path solver with the shoot
cache and the path-buffer watch (:class:`~caviar_plugins.rt.solver.PathTracer`).
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Callable, Collection, Sequence
from typing import Any, ClassVar

import numpy as np

from caviar_plugins.assets import SCENES
from caviar_plugins.radio.beams import beam_gains, dft_codebook, flat_dft_codebook
from caviar_plugins.radio.link_report import line_of_sight_paths
from caviar_plugins.radio.path_data import PathData, receiver_paths
from caviar_plugins.rt.materials import apply_materials
from caviar_plugins.rt.scene import (
    OUT_OF_THE_WAY_M,
    AntennaArray,
    Emitter,
    MovingObjects,
    build_scene,
    itu_material,
    move_objects,
    receiver,
    scene_object,
)
from caviar_plugins.rt.settings import TraceSettings, moved_keys

CODEBOOKS = ("kronecker", "flat-dft")
UAV_BODY = SCENES / "central_park" / "meshes" / "Cube.ply"  # a 2 m cube


@dataclasses.dataclass
class RadioConfig:
    """The paper's communications parameters (Table "Communications parameters")."""

    scene: str = "central_park"
    frequency_hz: float = 40e9
    tx_position: list[float] = dataclasses.field(default_factory=lambda: [-154.0, 64.0, 120.0])
    tx_orientation: list[float] = dataclasses.field(default_factory=lambda: [-2.0944, 0.785398, 0.0])
    """Yaw, pitch, roll in radians."""
    tx_array: list[int] = dataclasses.field(default_factory=lambda: [8, 8])
    """Rows (along z) × columns (along y)."""
    rx_array: list[int] = dataclasses.field(default_factory=lambda: [2, 2])
    spacing: float = 0.5
    """Element spacing in wavelengths, both axes."""
    pattern: str = "tr38901"
    polarization: str = "V"
    raytracing: TraceSettings = dataclasses.field(default_factory=TraceSettings)
    """How rays are traced (``raytracing = { samples_per_src, max_depth, los, ...,
    threads, shoot_cache, max_num_paths_per_src }``): see
    :class:`~caviar_plugins.rt.settings.TraceSettings`. Here 1e6 rays per source to depth 5
    with every interaction (the paper's). The shoot cache covers one transmitter's solves;
    UAV bodies and the objects of :meth:`RadioScene.add_moving_objects` (vehicles) move on
    top of it (``cache_moving_bodies``); other changes of the geometry and the first solve
    of a geometry run Sionna's loop unchanged."""
    uav_mesh: bool = True
    """Put a metal UAV body (the scene's 2 m cube) at each UAV's position."""
    antenna_offset: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 1.5])
    """Receive antenna relative to the UAV body's centre (above the 2 m cube)."""
    rx_orientation: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    """Receivers' yaw, pitch, roll in radians."""
    codebook: str = "kronecker"
    """``kronecker``: a 2-D DFT grid of beams per planar array (unit-norm codewords);
    ``flat-dft``: the 2023 code's unnormalised N-point DFT over the flat element index
    (see :func:`~caviar_plugins.radio.beams.flat_dft_codebook`)."""
    normalize: bool = False
    """Scale each link's H to unit mean |H_mn|² (the 2023 code's ``normalize=True``):
    path loss and distance cancel. A link without paths stays zero."""
    cache_moving_bodies: bool = True
    """With ``shoot_cache`` and ``uav_mesh``: the UAV bodies are moving objects on top of
    the cached bounces of the static scene, so solves are served from the cache while they
    move. Each solve's visibility tests and Sionna's image method run with the bodies where
    they are (the paths they block are dropped); the paths by way of a body come from rays
    aimed at it from the transmitter and from the recorded rays that now meet it after a
    bounce, bounced on in the scene as it is (:mod:`~caviar_plugins.rt.shoot_cache`).
    A diffuse path whose earlier segments now meet a body is dropped. Measured
    against Sionna's loop in docs/measured/performance.md. ``false``: a moved body is a
    new geometry, and the solve runs Sionna's loop. ``sionna-traffic-link`` treats its vehicles and persons the
    same way."""
    rays_per_moving_object: int = 4096
    """Rays aimed from the transmitter at each moving body's bounding sphere per solve
    (with ``cache_moving_bodies``): 4096 put them about 5 cm apart on a 2 m UAV body, where
    Sionna's 1e6 rays over the whole sphere are about 1.3 m apart at 200 m. 0: none aimed;
    Sionna's own rays from the transmitter that now meet the object first go on from it (the
    rays of Sionna's loop, with the same seed: a car 50 m away gets about 60 of 1e5)."""
    moved: ClassVar[dict[str, str]] = moved_keys()
    """The keys that moved into ``raytracing`` (refused flat, with the new key named)."""

    def __post_init__(self):
        if self.codebook not in CODEBOOKS:
            raise ValueError(f"codebook: expected one of {', '.join(CODEBOOKS)}, got {self.codebook!r}")
        for name in ("tx_position", "tx_orientation", "antenna_offset", "rx_orientation"):
            if len(getattr(self, name)) != 3:
                raise ValueError(f"{name}: expected three numbers, got {getattr(self, name)}")
        for name in ("tx_array", "rx_array"):
            if len(getattr(self, name)) != 2 or min(getattr(self, name)) < 1:
                raise ValueError(f"{name}: expected [rows, columns], got {getattr(self, name)}")
        if self.rays_per_moving_object < 0:
            raise ValueError(f"rays_per_moving_object: expected >= 0 (0: Sionna's own rays), got "
                             f"{self.rays_per_moving_object}")


@dataclasses.dataclass
class Link:
    """One receiver's result of a solve."""

    h: np.ndarray
    """Narrowband MIMO channel at the carrier, (N_rx_ant, N_tx_ant) complex."""
    gains: np.ndarray
    """Beam-pair gains |w_rx^H H w_tx|², (C_rx, C_tx)."""
    los: bool
    n_paths: int
    paths_dropped: int = 0
    """Candidate paths of this solve that Sionna's buffer (``max_num_paths_per_src``)
    could not hold and dropped: when > 0 the channel may miss paths."""
    paths: PathData | None = None
    """The receiver's paths (coefficients, delays, angles, interactions), when the scene
    keeps them (:attr:`RadioScene.keep_paths`)."""

    @property
    def path_gain(self) -> float:
        """Mean power gain over antenna pairs (element patterns included)."""
        return float(np.mean(np.abs(self.h) ** 2))

    @property
    def best_pair(self) -> int:
        """Flat index rx_beam · C_tx + tx_beam of the strongest pair."""
        return int(np.argmax(self.gains))


def radio_config(params: Any, **changes: Any) -> RadioConfig:
    """The :class:`RadioConfig` part of a plugin's parameters (a dataclass that extends
    it), with ``changes``: a new object, the parameters stay as the configuration gave them."""
    names = {f.name for f in dataclasses.fields(RadioConfig)}
    values = {f.name: getattr(params, f.name) for f in dataclasses.fields(params) if f.name in names}
    return RadioConfig(**{**values, **changes})


def normalize_channel(h: np.ndarray) -> np.ndarray:
    """H scaled to unit mean |H_mn|² (Sionna 0.15's ``cir_to_ofdm_channel(normalize=True)``
    for one frequency); an all-zero H stays zero."""
    c = float(np.mean(np.abs(h) ** 2))
    return h / np.sqrt(c) if c > 0 else h


class RadioScene:
    def __init__(self, cfg: RadioConfig, seed: int = 0, base_dir: pathlib.Path | None = None):
        from caviar_plugins.rt.solver import PathTracer

        self.cfg = cfg
        self.seed = int(seed)
        """The run's seed (the solver's is ``raytracing.seed`` where set)."""
        self.scene = build_scene(cfg.scene, base_dir, frequency_hz=cfg.frequency_hz,
                                 tx_array=self._array(cfg.tx_array), rx_array=self._array(cfg.rx_array),
                                 transmitters=[Emitter("tx", cfg.tx_position, cfg.tx_orientation)],
                                 threads=cfg.raytracing.threads)
        s = self.scene
        self.movers = MovingObjects(s, enabled=cfg.cache_moving_bodies, rays_per_object=cfg.rays_per_moving_object)
        """The UAV bodies (``movers.bodies``) and the objects of :meth:`add_moving_objects`."""
        self.tracer = PathTracer(s, cfg.raytracing, seed=self.seed, movers=self.movers)
        if cfg.codebook == "flat-dft":
            self.w_tx = flat_dft_codebook(s.tx_array.num_ant)
            self.w_rx = flat_dft_codebook(s.rx_array.num_ant)
        else:
            self.w_tx = dft_codebook(np.array(s.tx_array.positions(s.wavelength)))
            self.w_rx = dft_codebook(np.array(s.rx_array.positions(s.wavelength)))
        self.receivers: dict[str, Any] = {}
        self.bodies = self.movers.bodies
        # The scene is static and the solver seeded: the same positions give the same
        # paths, so a step in which no UAV moved (hovering) reuses the last solve.
        self._placed: tuple = ()
        self._body_at: dict[str, np.ndarray] = {}  # receiver key -> where its body is
        self._where: dict[str, np.ndarray] = {}  # receiver key -> its position (antenna offset added)
        self._solved: tuple[tuple, dict] | None = None
        self.solves = 0
        """Solves that traced (not those that reused the last one)."""
        self._body_template = s.objects.get("Cube")
        self._bodies_on = cfg.uav_mesh
        self.materials: dict[str, dict[str, float]] = {}
        """The material properties set after loading (:meth:`set_materials`)."""
        self.keep_paths = False
        """Attach every receiver's :class:`~caviar_plugins.radio.path_data.PathData` to its
        :class:`Link` (costs the paths' interactions and vertices on each solve)."""

    def set_materials(self, values: dict[str, dict[str, float]]) -> None:
        """Sets radio material properties (``{material: {property: value}}``, e.g. what a
        ``scene-fitter`` learned; :func:`~caviar_plugins.rt.materials.apply_materials`) from
        the next solve on; they are kept in :meth:`snapshot`."""
        apply_materials(self.scene, values)
        for name, props in values.items():
            self.materials.setdefault(name, {}).update(props)
        self._solved = None

    @property
    def shoot_cache(self):
        """The path tracer's shoot cache (None: Sionna's own loop)."""
        return self.tracer.shoot_cache

    @property
    def last_paths(self) -> Any:
        """Sionna's ``Paths`` of the last solve that traced (amplitudes, delays, Doppler shifts...)."""
        return self.tracer.last_paths

    def moving_objects(self) -> list[Any]:
        """The objects the shoot cache handles on top of its recorded bounces (the UAV
        bodies and the objects of :meth:`add_moving_objects`, with ``cache_moving_bodies``);
        the geometry fingerprint leaves them out."""
        return self.movers.present()

    def add_moving_objects(self, objects: Sequence[Any], away: Callable[[Any], bool] | None = None,
                           boxes: Callable[[Any], np.ndarray] | None = None) -> None:
        """Declares scene objects that a caller moves from solve to solve (vehicles,
        persons): with ``cache_moving_bodies`` the shoot cache keeps serving solves while
        they move, as it does for UAV bodies; without it, their moves make every solve a new
        geometry. ``away(obj)`` says whether an object is out of the scene for now (parked):
        no rays are aimed at it. ``boxes(obj)`` (an object made of separate bodies, as a
        :class:`~caviar_plugins.rt.scatterers.ScattererPool`'s mesh) gives the bounds
        (m, 2, 3) of each of its bodies, which the shoot cache then treats one by one;
        without it, the object's bounding box. Declaring an object again does nothing."""
        self.movers.declare(objects, away, boxes)

    def cache_status(self) -> str | None:
        """One line on what share of the solves the shoot cache served (None without it or
        before the first solve), for ``caviar.status``."""
        return self.tracer.cache_status(self.solves)

    def paths_dropped(self) -> int:
        """Candidates the last solve dropped for lack of buffer (0: none)."""
        return self.tracer.paths_dropped()

    def _array(self, shape) -> AntennaArray:
        return AntennaArray(rows=shape[0], cols=shape[1], spacing=self.cfg.spacing, pattern=self.cfg.pattern,
                            polarization=self.cfg.polarization)

    @property
    def n_tx_beams(self) -> int:
        return self.w_tx.shape[1]

    def place(self, positions: dict[str, np.ndarray], park: Collection[str] = ()) -> None:
        """Moves (creating on first sight) each UAV's receiver and body. One that is
        where it was is left alone: moving bodies updates the scene's geometry (about
        12 ms in the SAR scene on the CPU), once for all the bodies that moved
        (:func:`~caviar_plugins.rt.scene.move_objects`), and a hovering UAV would pay it every step.
        ``park``: keys whose receivers are placed but whose bodies are put out of the way,
        :data:`~caviar_plugins.rt.scene.OUT_OF_THE_WAY_M` below (look-ahead: a slot where
        another slot of the same UE already has the body)."""
        new = [k for k in positions if k not in self.receivers]
        if new and self._bodies_on:
            self._add_bodies(new)
        offset = np.asarray(self.cfg.antenna_offset, dtype=float)
        bodies = []
        for key, pos in positions.items():
            pos = np.asarray(pos, dtype=float)
            moved = key not in self._where or not np.array_equal(self._where[key], pos + offset)
            if key not in self.receivers:
                rx = receiver(f"rx-{key}", (pos + offset).tolist(), self.cfg.rx_orientation)
                self.scene.add(rx)
                self.receivers[key] = rx
            elif moved:
                self.receivers[key].position = (pos + offset).tolist()
            if key in self.bodies:  # (a body is where its receiver is, less the antenna offset)
                body = pos - [0.0, 0.0, OUT_OF_THE_WAY_M] if key in park else pos
                if key not in self._body_at or not np.array_equal(self._body_at[key], body):
                    bodies.append((self.bodies[key], body))
                    self._body_at[key] = body
                self.movers.set_away(self.bodies[key], key in park)
            self._where[key] = pos + offset
        move_objects(self.scene, bodies)  # (one geometry update for all)
        self._placed = tuple((k, tuple(np.asarray(p, dtype=float))) for k, p in positions.items())

    def snapshot(self) -> dict[str, Any]:
        """What a checkpoint keeps of the scene: every receiver in the scene's order at the
        UE position it was last placed at (stale ones too: they are traced with the others),
        the last placement and solve (a step in which nothing moved reuses it), whether
        the shoot cache had seen the current geometry, and the size the tracer grew Sionna's
        chain table to. Picklable; see :meth:`restore`."""
        offset = np.asarray(self.cfg.antenna_offset, dtype=float)
        return {"receivers": [(k, self._where[k] - offset) for k in self.receivers],
                "placed": self._placed, "solved": self._solved,
                "geometry_seen": self.tracer.cache_seen, "materials": self.materials,
                "chain_slots": self.tracer.chain_slots,
                "counts": (self.solves, *((self.shoot_cache.connects, self.shoot_cache.shoots)
                                          if self.shoot_cache is not None else ()))}

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Rebuilds :meth:`snapshot`'s state in a freshly set-up scene: the receivers and
        UAV bodies where they were, and, when the shoot cache had seen this geometry, one
        solve that lets it see it again, so the next solve is served as it would have been."""
        if snapshot.get("materials"):
            self.set_materials(snapshot["materials"])
        self.tracer.chain_slots = int(snapshot.get("chain_slots", 0))  # (a grown table stays grown)
        if snapshot["receivers"]:
            self.place(dict(snapshot["receivers"]))
            if snapshot["geometry_seen"]:
                self._solved = None
                self.solve()
        self._placed, self._solved = snapshot["placed"], snapshot["solved"]
        counts = snapshot.get("counts", ())
        if counts:
            self.solves = counts[0]
        if len(counts) == 3 and self.shoot_cache is not None:
            self.shoot_cache.connects, self.shoot_cache.shoots = counts[1], counts[2]

    def remove(self, keys) -> None:
        """Takes the receivers of ``keys`` (never UAV bodies) out of the scene."""
        for key in keys:
            if key in self.receivers:
                self.scene.remove(f"rx-{key}")
                del self.receivers[key], self._where[key]
        self._placed = tuple((k, p) for k, p in self._placed if k in self.receivers)
        self._solved = None

    def _add_bodies(self, keys: list[str]) -> None:
        # The scene's own UAV cube serves the first UAV; more UAVs (and scenes without
        # one) get a copy of the shipped 2 m cube in ITU metal, added in one edit: an
        # edit recompiles kernels, so it happens only when UAVs appear.
        extra = []
        for key in keys:
            template = self._body_template
            if template is not None and all(b is not template for b in self.bodies.values()):
                self.bodies[key] = template
                continue
            material = template.radio_material if template is not None else self._metal()
            obj = scene_object(UAV_BODY, f"uav-body-{key}", material)
            extra.append(obj)
            self.bodies[key] = obj
        if extra:
            self.scene.edit(add=extra)

    def _metal(self):
        if not hasattr(self, "_metal_material"):
            self._metal_material = itu_material("uav-metal", "metal", thickness=0.1)
        return self._metal_material

    def solve(self, force: bool = False) -> dict[str, Link]:
        """Ray traces every receiver in one call (or reuses the last result if no receiver
        moved, unless ``force``: for a caller that moved objects of the scene itself);
        returns the links of the receivers the last :meth:`place` placed. The traced
        paths stay in :attr:`last_paths`."""
        if not force and self._solved is not None and self._solved[0] == self._placed:
            return self._solved[1]
        c = self.cfg
        self.solves += 1
        paths = self.tracer.solve()
        dropped = self.tracer.dropped
        # Every receiver of the scene was traced, in the scene's order (which is not the
        # order of the last place(): UEs that joined later come last).
        from caviar_plugins.rt.solver import carrier_channels

        h, valid, tau = carrier_channels(paths, len(self.receivers), c.frequency_hz)
        rx_pos = np.array([self._where[key] for key in self.receivers])
        direct = np.linalg.norm(rx_pos - np.asarray(c.tx_position, dtype=float), axis=1)
        los = np.any(line_of_sight_paths(tau, valid, direct[:, None]), axis=1)
        found = receiver_paths(paths, self.scene, c.tx_position, rx_pos, c.frequency_hz) if self.keep_paths else None
        power = np.mean(np.abs(h) ** 2, axis=(1, 2))
        if c.normalize:
            h = np.where(power[:, None, None] > 0, h / np.sqrt(np.where(power > 0, power, 1.0))[:, None, None], h)
        gains = beam_gains(h, self.w_tx, self.w_rx)  # (every receiver in one product)
        n_paths = valid.sum(axis=1)
        out = {}
        for i, key in enumerate(self.receivers):
            if found is not None:
                found[i].h_scale = 1 / np.sqrt(power[i]) if c.normalize and power[i] > 0 else 1.0
            out[key] = Link(h=h[i], gains=gains[i], los=bool(los[i]), n_paths=int(n_paths[i]), paths_dropped=dropped,
                            paths=None if found is None else found[i])
        placed = {k for k, _ in self._placed}
        out = {k: link for k, link in out.items() if k in placed}
        self._solved = (self._placed, out)
        return out


LOOKAHEAD_AUTO = {"GPU": (40, 9), "CPU": (30, 9)}
"""``lookahead_steps = "auto"``, by Dr.Jit backend: (about how many receivers one look-ahead
solve traces, the most steps ahead). On a GPU a solve is bound by host work that grows
slowly with the receivers (H200: 39 ms for 1, 117 ms for 10), so a solve traces more
receivers; on the CPU the shoot cache's cost grows with them (0.08x of Sionna's loop for 1,
0.36x for 10; bench_perf_steps measured 9 steps best for 1 UAV and 2 for 10). At most 9
steps: with the UAV bodies, each slot's receiver sees the other slots' bodies, and on the
CPU (1 UAV, 40 steps, bench_solve_host) 19 steps ahead erred by up to 9.0 dB of path gain
against every-step tracing where 9 steps erred by 2.7 dB and 4 steps by 3.1 dB (another
seed: 3.9 dB), for 31, 39 and 62 ms a step against 118 ms."""


def lookahead_depth(steps: int | str, n_ue: int, variant: str | None = None) -> int:
    """The forecast positions a look-ahead solve traces per UE: ``steps``, or for ``"auto"``
    the receivers of :data:`LOOKAHEAD_AUTO` for the backend shared by ``n_ue`` UEs (at least
    1, at most its most steps). ``variant``: the Mitsuba variant (default: the active one)."""
    if steps != "auto":
        return int(steps)
    if variant is None:
        from caviar_plugins.rt.drjit_setup import mitsuba

        variant = str(mitsuba().variant())
    budget, most = LOOKAHEAD_AUTO["GPU" if variant.startswith("cuda_") else "CPU"]  # (Dr.Jit's CUDA or LLVM)
    return max(1, min(most, budget // max(n_ue, 1) - 1))


def check_lookahead_steps(value: Any, key: str = "lookahead_steps") -> int | str:
    """``value`` if it is a look-ahead depth (an integer >= 0 or ``"auto"``), else a
    ValueError naming ``key``."""
    if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
        return value
    raise ValueError(f'{key}: expected an integer >= 0 or "auto", got {value!r}')


class LookaheadTracer:
    """Look-ahead ray tracing: one solve traces every UE's current position and its
    forecast (the next ``steps`` positions its mobility module expects; ``"auto"``:
    :func:`lookahead_depth`), and caches each position's :class:`Link`. A later step whose
    positions are all within ``tolerance_m`` of cached ones (a forecast that came true, a
    hovering UAV) costs no solve; otherwise (a UE left its forecast, or the forecast is used
    up) one new solve traces all UEs again. Receivers are ``steps + 1`` per UE in every solve
    (a missing forecast is padded with the last position): stable shapes, reused kernels.

    Without UAV bodies (``uav_mesh = false``) this is exact: a position's paths do not
    depend on the other receivers of the solve (same rays, same seed). With them, each
    forecast position (slot) has a body of its own under its receiver, so every receiver
    has its own UAV's body where it will be; it also sees the bodies of the other slots
    (its own UAV a step or more along its route, 2 m cubes below the antenna's height) and
    of the other UAVs at every slot. A slot at the position of an earlier slot of the same
    UE (hovering, padding) has its body parked out of the way. Measured against solving
    step by step in tests/test_solve_lookahead.py."""

    def __init__(self, radio: RadioScene, steps: int | str, tolerance_m: float = 0.01):
        check_lookahead_steps(steps)
        if tolerance_m < 0:
            raise ValueError(f"cache_tolerance_m: expected >= 0, got {tolerance_m}")
        self.radio, self.steps, self.tolerance_m = radio, steps, tolerance_m
        self.cache: dict[str, list[tuple[np.ndarray, Link]]] = {}
        self.solves = 0
        self.hits = 0
        self._slots: dict[str, np.ndarray] = {}  # the last solve's receivers: key -> UE position

    def state(self) -> dict[str, Any]:
        """The cached links and counters, for a checkpoint (the scene keeps its own)."""
        return {"cache": self.cache, "solves": self.solves, "hits": self.hits, "slots": self._slots}

    def restore(self, state: dict[str, Any]) -> None:
        self.cache, self.solves, self.hits = state["cache"], state["solves"], state["hits"]
        self._slots = state.get("slots", {})

    def lookup(self, ue: str, position) -> Link | None:
        p = np.asarray(position, dtype=float)
        best, best_d = None, self.tolerance_m
        for q, link in self.cache.get(ue, []):
            d = float(np.linalg.norm(q - p))
            if d <= best_d:
                best, best_d = link, d
        return best

    def links(self, current: dict[str, np.ndarray], forecast: dict[str, list] | None = None) -> dict[str, Link]:
        """Each UE's link at its current position, from the cache or from one new solve."""
        forecast = forecast or {}
        cached = {ue: self.lookup(ue, p) for ue, p in current.items()}
        if all(link is not None for link in cached.values()):
            self.hits += 1
            return {ue: link for ue, link in cached.items() if link is not None}
        steps = lookahead_depth(self.steps, len(current))
        slots: dict[str, np.ndarray] = {}
        park: set[str] = set()
        for ue, p in current.items():
            ahead = [np.asarray(q, dtype=float) for q in forecast.get(ue, [])][:steps]
            seq = [np.asarray(p, dtype=float), *ahead]
            seq += [seq[-1]] * (steps + 1 - len(seq))
            for k, q in enumerate(seq):
                slots[f"{ue}@{k}"] = q
                if any(np.array_equal(q, seq[j]) for j in range(k)):  # (its body is already there)
                    park.add(f"{ue}@{k}")
        stale = {key: p for key, p in self._slots.items() if key not in slots}  # (the depth changed)
        if stale:
            self.radio.place(stale, park=set(stale))
            self.radio.remove(stale)
        self._slots = slots
        self.radio.place(slots, park=park)
        links = self.radio.solve()
        self.solves += 1
        self.cache = {ue: [(slots[f"{ue}@{k}"], links[f"{ue}@{k}"]) for k in range(steps + 1)]
                      for ue in current}
        return {ue: links[f"{ue}@0"] for ue in current}
