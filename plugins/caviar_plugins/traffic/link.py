"""The ``sionna-traffic-link`` communications plugin: ``sionna-link`` in a living scene.

Every vehicle and person on ``3D.mobility.positions`` that carries ``dimensions`` (as
``sumo-traffic`` publishes them) is a box of its size in the ray-traced scene — ITU metal
for vehicles, ITU concrete for pedestrians by default — borrowed from a pool of boxes
added once at setup (:class:`~caviar_plugins.rt.scatterers.ScattererPool`): boxes move
every step without reloading the scene or recompiling the solver.

Receivers, one per UE, as in ``sionna-link``:

* UEs without ``dimensions`` (a UAV of ``waypoint-flight``): the antenna at the position
  plus ``antenna_offset``, with a metal body (a 2 m box) when ``uav_mesh``;
* connected vehicles: those named in ``connected`` and the first ``connected_count``
  vehicles of ``connected_types`` to appear; the antenna ``roof_antenna_m`` above the
  roof centre. Their receivers exist from setup on (parked below the ground while their
  vehicle is away), so the number of receivers never changes.

Each receiver moves with its UE's velocity (payload ``velocity``; for UEs without one, the
displacement since the previous step over the elapsed time), so Sionna RT gives every
path its Doppler shift. Per UE and step it publishes what ``sionna-link`` does, and on
``communications.link`` also ``doppler_hz`` (strongest path), ``doppler_los_hz`` (the
line-of-sight path, or null), ``speed`` and ``blocker``: what the straight Tx–Rx line hits
first — null when clear, the UE_Id of a vehicle/person, or ``"scene"`` for a building or
other static geometry.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

import caviar
from caviar_plugins.radio.link_budget import LinkBudget
from caviar_plugins.radio.link_report import LINK_TOPICS, line_of_sight_paths, link_messages
from caviar_plugins.radio.scene import RadioConfig, RadioScene, radio_config
from caviar_plugins.radio.sionna_link import LinkBudgetParams
from caviar_plugins.rt.scatterers import Body, ScattererPool, box_doppler_hz, update_pools
from caviar_plugins.rt.scene import itu_material
from caviar_plugins.schema import BEAM_SELECTION, POSITIONS, STATE, read_position

PARKED_RX_Z = -500.0
UAV_BODY_SIZE = (2.0, 2.0, 2.0)
ITU_TYPES = ("concrete", "brick", "plasterboard", "wood", "glass", "ceiling_board", "chipboard", "plywood",
             "marble", "floorboard", "metal", "very_dry_ground", "medium_dry_ground", "wet_ground")


@dataclasses.dataclass
class SionnaTrafficLinkParams(LinkBudgetParams, RadioConfig):
    """The ray-traced link's parameters (:class:`~caviar_plugins.radio.scene.RadioConfig`,
    the link budget) and the traffic's. Differences from ``sionna-link``: a UAV's body is a
    box of a pool (``uav_mesh`` says whether UAVs get one; ``antenna_offset`` is the
    antenna above that box's centre), and with ``scatterers`` the shoot cache serves solves
    only with ``cache_moving_bodies`` (moving boxes on top of the recorded bounces)."""

    vehicle_pool: int = 64
    """Boxes for vehicles, made at setup: the most vehicles in the scene at once. More
    vehicles grow the pool (one scene edit and recompile, with a warning)."""
    person_pool: int = 32
    """Boxes for pedestrians, likewise."""
    vehicle_material: str = "metal"
    """ITU-R P.2040 material of vehicle boxes (Sionna ``itu_<name>``)."""
    person_material: str = "concrete"
    """Of pedestrian boxes. P.2040 has no body tissue; concrete (thickness ``person_thickness``)
    is opaque at mm-wave like a body and reflects about as weakly (normal incidence: −8 dB
    for concrete against about −5 dB for skin at 40 GHz)."""
    person_thickness: float = 0.3
    connected: list[str] = dataclasses.field(default_factory=list)
    """UE_Ids of vehicles that are receivers (e.g. SUMO ids)."""
    connected_count: int = 0
    """Plus the first N vehicles of ``connected_types`` to appear."""
    connected_types: list[str] = dataclasses.field(default_factory=lambda: ["car"])
    roof_antenna_m: float = 0.1
    """A connected vehicle's antenna above its roof."""
    scatterers: bool = True
    """Vehicles and persons as boxes in the scene (false: receivers only)."""
    rays_per_moving_object: int = 0
    """With the shoot cache (``cache_moving_bodies``), the rays aimed at each box per solve;
    0 (here the default): none aimed, Sionna's own rays from the transmitter that now meet a
    box first go on from it, so that the paths by way of vehicles are those of Sionna's loop
    (a car 50 m away gets about 60 of 1e5)."""

    def __post_init__(self):
        super().__post_init__()
        for name in ("vehicle_material", "person_material"):
            if getattr(self, name) not in ITU_TYPES:
                raise ValueError(f"{name}: expected an ITU-R P.2040 material ({', '.join(ITU_TYPES)}), "
                                 f"got {getattr(self, name)!r}")
        if self.vehicle_pool < 0 or self.person_pool < 0 or self.connected_count < 0:
            raise ValueError("vehicle_pool, person_pool and connected_count must be >= 0")


class SionnaTrafficLink(caviar.Plugin):
    subscribe = [POSITIONS, BEAM_SELECTION]
    optional = (BEAM_SELECTION,)  # (without it: the best pair)
    publishes = (*LINK_TOPICS, STATE, caviar.STATUS_TOPIC)
    Params = SionnaTrafficLinkParams

    def setup(self, ctx):
        from caviar_plugins.rt.solver import use_shoot_cache

        p = ctx.params
        self.p = p
        self.ctx = ctx
        self.uav_offset = np.asarray(p.antenna_offset, dtype=float)
        # Receivers are placed at their antennas here and UAV bodies are boxes of the pool.
        # The pools' boxes are the shoot cache's moving objects (cache_moving_bodies): the
        # bounces of the static scene are recorded once and the boxes handled on top of them.
        # Without cache_moving_bodies every step would be a new geometry: no cache then.
        cached = use_shoot_cache(p.raytracing.shoot_cache) and (p.cache_moving_bodies or not p.scatterers)
        radio_cfg = radio_config(p, antenna_offset=[0.0, 0.0, 0.0], uav_mesh=False,
                                 raytracing=dataclasses.replace(p.raytracing, shoot_cache=cached))
        self.radio = RadioScene(radio_cfg, seed=ctx.seed, base_dir=ctx.config_dir)
        self.budget = LinkBudget(bandwidth_hz=p.bandwidth_hz, tx_power_w=p.tx_power_w,
                                 interference_dbw=p.interference_dbw)
        n_slots = len(p.connected) + p.connected_count
        capacity = {"vehicle": p.vehicle_pool, "person": p.person_pool} if p.scatterers else {}
        self.pool_edits: list[tuple[str, dict[str, int]]] = []  # both pools' growth, in order (checkpoints)
        self.pool = ScattererPool(self.radio.scene, capacity, {
            "vehicle": itu_material("traffic-vehicle", p.vehicle_material, thickness=0.01),
            "person": itu_material("traffic-person", p.person_material, thickness=p.person_thickness),
        }, prefix="traffic", edits=self.pool_edits)
        self.uav_pool: ScattererPool | None = None
        self._declare_movers()
        self.rx_slots = [f"car-slot-{i}" for i in range(n_slots)]
        self.slot_of: dict[str, str] = {}  # connected vehicle -> receiver slot
        self.rx_pos: dict[str, np.ndarray] = {}  # receiver key -> antenna position (insertion order = receivers)
        self.rx_vel: dict[str, np.ndarray] = {}
        park = np.array([0.0, 0.0, PARKED_RX_Z])
        for i, slot in enumerate(self.rx_slots):
            self.rx_pos[slot] = park + [i, 0.0, 0.0]
            self.rx_vel[slot] = np.zeros(3)
        self.ue_type: dict[str, str] = {}
        self.selected: dict[str, int] = {}
        self.prev: dict[str, tuple[float, np.ndarray]] = {}  # for UEs without velocity
        self.n_chosen = 0

    # -- per step -----------------------------------------------------------------

    def _read(self, t, inbox):
        """Bodies in the scene and receivers to serve this step (UE -> (receiver, antenna
        position, velocity)), from the inbox."""
        bodies, served, vehicles = [], {}, {}
        for m in inbox:
            if m.topic == BEAM_SELECTION:
                self.selected[m.data["UE_Id"]] = int(m.data["beam_pair"])
            elif m.topic == POSITIONS:
                ue, pos, vel = self._ue(t, m.data)
                dims = m.data.get("dimensions")
                if dims is None:  # a UAV (or any UE without a size): a receiver of its own
                    served[ue] = (ue, pos + self.uav_offset, vel)
                    if self.p.uav_mesh:
                        centre = pos - [0.0, 0.0, UAV_BODY_SIZE[2] / 2]
                        bodies.append(Body(ue, "uav", tuple(centre), 0.0, UAV_BODY_SIZE, tuple(vel)))
                    continue
                size = (float(dims["length"]), float(dims["width"]), float(dims["height"]))
                group = "person" if m.data["UE_type"] == "pedestrian" else "vehicle"
                if self.p.scatterers:
                    bodies.append(Body(ue, group, tuple(pos), float(m.data.get("heading", 0.0)), size, tuple(vel)))
                if group == "vehicle":
                    vehicles[ue] = (pos + [0.0, 0.0, size[2] + self.p.roof_antenna_m], vel)
        # Connected vehicles: the named ones, and the first of the chosen types to appear.
        for ue in sorted(vehicles):
            if ue not in self.slot_of:
                named = ue in self.p.connected
                if not named and (self.n_chosen >= self.p.connected_count
                                  or self.ue_type[ue] not in self.p.connected_types):
                    continue
                self.slot_of[ue] = self.rx_slots[len(self.slot_of)]
                self.n_chosen += 0 if named else 1
            served[ue] = (self.slot_of[ue], *vehicles[ue])
        return bodies, served

    def _ue(self, t, d):
        ue, pos = d["UE_Id"], read_position(d)
        self.ue_type[ue] = d["UE_type"]
        v = d.get("velocity")
        if v is not None:
            vel = np.array([v["x"], v["y"], v["z"]], dtype=float)
        else:  # from the displacement since the last step
            t0, p0 = self.prev.get(ue, (t, pos))
            vel = (pos - p0) / (t - t0) if t > t0 else np.zeros(3)
        self.prev[ue] = (t, pos)
        return ue, pos, vel

    def step(self, t, inbox):
        bodies, served = self._read(t, inbox)
        self._place_bodies(bodies)
        for slot, _, _ in served.values():
            if slot not in self.rx_pos:  # a new UAV: one more receiver (a recompile, once)
                self.rx_pos[slot] = np.zeros(3)
                self.rx_vel[slot] = np.zeros(3)
        active = {slot for slot, _, _ in served.values()}
        for i, slot in enumerate(self.rx_pos):
            if slot not in active:  # a connected car that left, a UAV not reported: parked
                self.rx_pos[slot] = np.array([float(i), 0.0, PARKED_RX_Z])
                self.rx_vel[slot] = np.zeros(3)
        for slot, pos, vel in served.values():
            self.rx_pos[slot] = np.asarray(pos, dtype=float)
            self.rx_vel[slot] = np.asarray(vel, dtype=float)
        if not served:
            return
        self.radio.place(self.rx_pos)
        for slot, rx in self.radio.receivers.items():
            rx.velocity = self.rx_vel[slot].tolist()
        links = self.radio.solve(force=True)  # the scatterers moved: never reuse the last solve
        self._add_box_doppler()
        extra_info = self._paths_info()
        blockers = self._blockers()
        n_pairs = self.radio.w_rx.shape[1] * self.radio.n_tx_beams

        def mbps(gain: float) -> float:
            return float(self.budget.throughput_mbps(gain))

        def snr(gain: float) -> float:
            return float(self.budget.sinr(gain))

        for ue in sorted(served):
            slot = served[ue][0]
            extra = {"speed": float(np.linalg.norm(self.rx_vel[slot])), "blocker": blockers[slot], **extra_info[slot]}
            yield from link_messages(self.ue_type[ue], ue, links[slot], self.selected.get(ue), n_pairs, mbps, snr,
                                     self.p.publish_channels, extra)
        yield STATE, "Ready"
        status = self.radio.cache_status()
        if status is not None:
            yield caviar.STATUS_TOPIC, status

    def _place_bodies(self, bodies):
        uav = [b for b in bodies if b.group == "uav"]
        others = [b for b in bodies if b.group != "uav"]
        if self.uav_pool is None and uav:
            # UAV bodies: a pool of their own the first time UAVs are seen (their receivers
            # are new then too, so this edit costs no extra recompile later).
            self._new_uav_pool({"uav": len(uav)})
        before = self.pool.capacity
        # Both pools' boxes in one scene update (one acceleration-structure rebuild).
        update_pools([*([(self.uav_pool, uav)] if self.uav_pool is not None else []), (self.pool, others)],
                     grow=True)
        self._declare_movers()  # (again after a pool grew: the new boxes move too)
        for group, n in self.pool.capacity.items():
            if n > before.get(group, 0):
                print(f"{self.ctx.name}: {group} pool grown from {before.get(group, 0)} to {n} boxes (one scene "
                      f"edit and recompile); set {group}_pool >= {n} to avoid it", file=sys.stderr)

    def _pools(self) -> list[ScattererPool]:
        """The traffic pool and, once UAVs were seen, theirs."""
        return [pool for pool in (self.pool, self.uav_pool) if pool is not None]

    def _declare_movers(self) -> None:
        for pool in self._pools():
            self.radio.add_moving_objects(pool.objects(), away=pool.parked, boxes=pool.boxes)

    def _new_uav_pool(self, capacity: dict[str, int]) -> None:
        self.uav_pool = ScattererPool(self.radio.scene, capacity,
                                      {"uav": itu_material("traffic-uav", "metal", thickness=0.01)},
                                      prefix="traffic-uav", edits=self.pool_edits)

    def state(self):
        # The scene, budget and pools' first boxes come from setup; the pools' growth (replayed
        # in order), their boxes, the receivers and what the UEs did are the state.
        return {"pool_edits": list(self.pool_edits), "pool": self.pool.snapshot(),
                "uav_pool": None if self.uav_pool is None else self.uav_pool.snapshot(),
                "slot_of": self.slot_of, "rx_pos": self.rx_pos, "rx_vel": self.rx_vel, "ue_type": self.ue_type,
                "selected": self.selected, "prev": self.prev, "n_chosen": self.n_chosen,
                "scene": self.radio.snapshot()}

    def restore(self, state):
        for prefix, more in state["pool_edits"][len(self.pool_edits):]:
            if prefix == self.pool.prefix:
                self.pool.grow(more)
            elif self.uav_pool is None:
                self._new_uav_pool(more)
            else:
                self.uav_pool.grow(more)
        self.pool.restore(state["pool"])
        if self.uav_pool is not None:
            self.uav_pool.restore(state["uav_pool"])
        self.slot_of, self.rx_pos, self.rx_vel = state["slot_of"], state["rx_pos"], state["rx_vel"]
        self.ue_type, self.selected, self.prev = state["ue_type"], state["selected"], state["prev"]
        self.n_chosen = state["n_chosen"]
        self._declare_movers()
        self.radio.restore(state["scene"])
        for slot, rx in self.radio.receivers.items():
            rx.velocity = self.rx_vel[slot].tolist()

    def _add_box_doppler(self) -> None:
        """Adds the Doppler shift of the moving boxes to the last paths (the pools' meshes
        have no velocity of their own in Sionna: see :class:`ScattererPool`)."""
        from caviar_plugins.rt import sionna_adapter as adapter

        pools = [pool for pool in self._pools() if pool.used]
        paths = self.radio.last_paths
        if not pools or paths is None:
            return
        extra = box_doppler_hz(pools, np.array(paths.interactions), np.array(paths.objects),
                               np.array(paths.primitives), np.array(paths.vertices),
                               np.array(paths.sources, dtype=float).reshape(3, -1).T,
                               np.array(paths.targets, dtype=float).reshape(3, -1).T,
                               float(np.asarray(self.radio.scene.wavelength).ravel()[0]))
        doppler = np.array(paths.doppler)
        adapter.set_doppler(paths, doppler + extra.reshape(doppler.shape))

    def _paths_info(self) -> dict[str, dict]:
        """Doppler of the strongest and of the line-of-sight path of each receiver."""
        paths = self.radio.last_paths
        keys = list(self.radio.receivers)
        n = len(keys)
        a_re, a_im = paths.a
        a2 = np.array(a_re) ** 2 + np.array(a_im) ** 2  # [rx, rx_ant, tx, tx_ant, paths]
        n_paths = a2.shape[-1]
        power = a2.reshape(n, -1, n_paths).sum(axis=1) if a2.size else np.zeros((n, n_paths))
        doppler = np.array(paths.doppler).reshape(n, n_paths)
        tau = np.array(paths.tau).reshape(n, n_paths)
        valid = np.array(paths.valid).reshape(n, n_paths).astype(bool)
        tx = np.asarray(self.radio.cfg.tx_position, dtype=float)
        out = {}
        for i, key in enumerate(keys):
            direct = float(np.linalg.norm(self.rx_pos[key] - tx))
            pw = np.where(valid[i], power[i], -1.0)
            best = int(np.argmax(pw)) if valid[i].any() else None
            los = np.flatnonzero(line_of_sight_paths(tau[i], valid[i], direct))
            out[key] = {"doppler_hz": float(doppler[i, best]) if best is not None else None,
                        "doppler_los_hz": float(doppler[i, los[0]]) if len(los) else None}
        return out

    def _blockers(self) -> dict[str, str | None]:
        """What the straight line from the transmitter to each receiver hits first."""
        from caviar_plugins.rt.scene import first_hits

        keys = list(self.radio.receivers)
        tx = np.asarray(self.radio.cfg.tx_position, dtype=float)
        rx = np.array([self.rx_pos[k] for k in keys])
        d = rx - tx
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-9)[:, None]
        hit, ids, prims = first_hits(self.radio.scene, np.repeat(tx[None], len(keys), axis=0), u,
                                     np.maximum(dist - 0.05, 0.0))
        pools = self._pools()

        def name(i: int) -> str:
            ues = (pool.key_at(ids[i], prims[i]) for pool in pools)
            return next((ue for ue in ues if ue is not None), "scene")

        return {k: (name(i) if hit[i] else None) for i, k in enumerate(keys)}


__all__ = ["SionnaTrafficLink", "SionnaTrafficLinkParams"]
