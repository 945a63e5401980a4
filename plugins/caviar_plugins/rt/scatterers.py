"""Moving scatterers in a Sionna RT scene: a pool of boxes that vehicles and pedestrians
borrow while they are in the scene.

The pool is added to the scene once (one ``scene.edit``, one kernel recompile), as one
mesh per group (material). After that an entity arriving takes a free box, one leaving
gives it back (parked 1 km below the ground, shrunk to 1 cm), and every step each mesh
with a box that moved gets its vertices rewritten in the Mitsuba scene parameters and the
acceleration structure is rebuilt once (one ``params.update()``): the scene is never
reloaded and, since the number of shapes and vertices does not change, the path solver's
kernels are reused.

Each box also carries its velocity. Sionna RT gives an object one velocity, so the meshes
have none: whoever solves adds the boxes' Doppler shifts to the paths with
:func:`box_doppler_hz` (``sionna-traffic-link`` does after every solve); a bare
``PathTracer.solve`` gives paths off the boxes no Doppler of their own.

Nothing of caviar here: :class:`ScattererPool` takes a ``sionna.rt.Scene``.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from caviar_plugins.rt.scene import geometry_changed, vertex_positions, write_vertex_positions

PARK_Z = -1000.0
PARK_SIZE = 0.01

# A unit box: footprint centred on the origin, from z = 0 to z = 1. Vertex i has
# x = ±0.5 (bit 0), y = ±0.5 (bit 1), z = 0 or 1 (bit 2).
_UNIT = np.array([[(i & 1) - 0.5, ((i >> 1) & 1) - 0.5, (i >> 2) & 1] for i in range(8)], dtype=float)


def _box_faces() -> np.ndarray:
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = []
    centre = np.array([0.0, 0.0, 0.5])
    for a, b, c, d in quads:
        for tri in ((a, b, c), (a, c, d)):
            v = _UNIT[list(tri)]
            n = np.cross(v[1] - v[0], v[2] - v[0])
            tris.append(tri if np.dot(n, v.mean(axis=0) - centre) > 0 else tri[::-1])  # outward
    return np.array(tris, dtype=np.uint32)


BOX_FACES = _box_faces()


@dataclasses.dataclass
class Body:
    """A box in the scene: ``center`` is the centre of its footprint on the ground."""

    key: str
    group: str
    """Which pool (material) it borrows from, e.g. ``vehicle`` or ``person``."""
    center: tuple[float, float, float]
    yaw: float
    """radians, counter-clockwise from x: the box's length lies along this direction."""
    size: tuple[float, float, float]
    """length, width, height in metres."""
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)


def box_vertices(center, yaw, size) -> np.ndarray:
    """The eight corners (8, 3) of a box of ``size`` (length, width, height) standing at
    ``center`` (footprint centre) and turned by ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = _UNIT * np.asarray(size, dtype=float)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rot.T + np.asarray(center, dtype=float)


class PoolFull(RuntimeError):
    pass


class ScattererPool:
    """``capacity[group]`` boxes of ``materials[group]`` (Sionna radio materials) added to
    ``scene`` in one edit, as one mesh per group.

    One mesh, not one per box: every Mitsuba shape of a scene is a target of the virtual
    calls that Sionna's solver traces (the surface interaction, the image method), and each
    is traced on every solve. 88 box meshes in the osm-traffic scene made its image method
    6x slower (33 against 5.7 ms, with as many paths). A box is 12 triangles of its group's
    mesh, the ``slot``-th (primitives ``12 slot`` to ``12 slot + 11``): :meth:`key_at` says
    whose box a hit is on.

    Velocities: Sionna RT gives an object one velocity, so each mesh has none (zero) and a
    box's velocity is added to the Doppler shifts of the paths that meet it afterwards
    (:func:`box_doppler_hz`, as Sionna computes it for an object's velocity)."""

    def __init__(self, scene, capacity: dict[str, int], materials: dict[str, object], prefix: str = "scatterer",
                 edits: list[tuple[str, dict[str, int]]] | None = None):
        import mitsuba as mi
        import sionna.rt as rt

        self.mi = mi
        self.scene = scene
        self.meshes: dict[str, Any] = {}  # group -> its SceneObject (all its boxes)
        self._group_of_mesh: dict[int, str] = {}  # id(SceneObject) -> group
        self.sizes: dict[str, int] = {}  # group -> boxes
        self.free: dict[str, list[int]] = {}
        self.used: dict[str, tuple[str, int]] = {}  # key -> (group, slot)
        self.state: dict[tuple[str, int], tuple | None] = {}  # what each slot shows now
        self.velocities: dict[str, np.ndarray] = {}  # group -> (boxes, 3) m/s
        self.rt = rt
        self.prefix = prefix
        self.materials = dict(materials)
        self.edits = 0
        self.last_update_s = 0.0
        self.last_changed = 0
        # Every grow (the first too) as (prefix, boxes added), in order; pools of one scene
        # may share the list: replayed in order, the same edits give the same object ids.
        self.edit_log = edits if edits is not None else []
        self.grow(capacity)

    def grow(self, more: dict[str, int]) -> None:
        """Adds ``more[group]`` boxes to each group, in one scene edit (a kernel recompile
        at the next solve): the group's mesh is replaced by a larger one showing the same."""
        mi = self.mi
        added, removed = [], []
        for group, n in more.items():
            if n <= 0:
                self.sizes.setdefault(group, 0)  # (a group with no boxes yet: PoolFull, or grown, later)
                self.free.setdefault(group, [])
                continue
            start = self.sizes.get(group, 0)
            size = start + n
            free = self.free.setdefault(group, [])
            name = f"{self.prefix}-{group}-boxes" + (f"-{self.edits}" if group in self.meshes else "")
            mesh = mi.Mesh(name, vertex_count=8 * size, face_count=len(BOX_FACES) * size,
                           has_vertex_normals=False, has_vertex_texcoords=False)
            p = mi.traverse(mesh)
            self.sizes[group] = size
            p["vertex_positions"] = mi.Float(self._vertices(group).ravel().tolist())
            faces = BOX_FACES[None] + (8 * np.arange(size, dtype=np.uint32))[:, None, None]
            p["faces"] = mi.UInt32(faces.ravel())
            p.update()
            obj = self.rt.SceneObject(mi_mesh=mesh, name=name, radio_material=self.materials[group])
            obj.velocity = [0.0, 0.0, 0.0]  # (the boxes' own: box_doppler_hz)
            if group in self.meshes:
                removed.append(self.meshes[group])
                del self._group_of_mesh[id(self.meshes[group])]
            self.meshes[group] = obj
            self._group_of_mesh[id(obj)] = group
            self.velocities[group] = np.r_[self.velocities.get(group, np.zeros((0, 3))), np.zeros((n, 3))]
            free[:0] = list(range(size - 1, start - 1, -1))  # pop() gives the lowest slot first
            added.append(obj)
        if added:
            self.scene.edit(add=added, remove=removed or None)
            self.edits += 1
        self.edit_log.append((self.prefix, dict(more)))

    def snapshot(self) -> dict:
        """The boxes' assignment and what each shows, for a checkpoint; :meth:`restore`
        shows it again in a pool grown to the same boxes (replay :attr:`edit_log` first)."""
        return {"free": {g: list(f) for g, f in self.free.items()}, "used": dict(self.used),
                "state": dict(self.state)}

    def restore(self, snapshot: dict) -> None:
        self.free = {g: list(f) for g, f in snapshot["free"].items()}
        self.used = dict(snapshot["used"])
        self._stage(dict(snapshot["state"]), every=True)
        geometry_changed(self.scene)

    @property
    def capacity(self) -> dict[str, int]:
        return dict(self.sizes)

    @property
    def slots(self) -> dict[str, range]:
        """Each group's box slots."""
        return {g: range(n) for g, n in self.sizes.items()}

    def update(self, bodies: list[Body], grow: bool = False) -> int:
        """Shows exactly ``bodies`` (others parked); returns how many boxes changed.
        A group with more bodies than boxes raises :class:`PoolFull`, or with ``grow``
        gets twice the boxes it needs (one scene edit, one recompile)."""
        return update_pools([(self, bodies)], grow)[0]

    def _vertices(self, group: str) -> np.ndarray:
        """The group's mesh vertices (boxes, 8, 3) as :attr:`state` says (parked where nothing)."""
        out = np.empty((self.sizes[group], 8, 3))
        for i in range(self.sizes[group]):
            state = self.state.get((group, i))
            out[i] = _PARKED if state is None else box_vertices(state[0], state[1], state[2])
        return out

    def _stage(self, wanted: dict[tuple[str, int], tuple], every: bool = False) -> int:
        """Writes the vertices of each group with a box whose state changed into the scene's
        parameters (without updating the scene); returns how many boxes changed."""
        changed = 0
        for group, n in self.sizes.items():
            here = 0
            for i in range(n):
                state = wanted.get((group, i))
                if self.state.get((group, i)) != state:
                    self.state[(group, i)] = state
                    self.velocities[group][i] = (0.0, 0.0, 0.0) if state is None else state[3]
                    here += 1
            if (here or every) and group in self.meshes:
                # (From a Python list: Dr.Jit copies it into memory of its own; a numpy array's memory
                # is taken as it is, and its alignment varies: about 10 % of the update, measured.)
                write_vertex_positions(self.scene, self.meshes[group], self._vertices(group).ravel().tolist())
            changed += here
        return changed

    def _assign(self, bodies: list[Body], grow: bool) -> dict[tuple[str, int], tuple]:
        """Frees the slots of bodies gone, gives new bodies a slot; (group, slot) -> state."""
        present = {b.key for b in bodies}
        for key in [k for k in self.used if k not in present]:
            group, slot = self.used.pop(key)
            self.free[group].append(slot)
        needed: dict[str, int] = {}
        for b in bodies:
            if b.key not in self.used:
                needed[b.group] = needed.get(b.group, 0) + 1
        for group, n in needed.items():
            if group not in self.sizes and not grow:
                raise KeyError(f"no scatterer pool for group {group!r} (pools: {', '.join(self.sizes)})")
            free = len(self.free.get(group, []))
            if n > free:
                if not grow:
                    raise PoolFull(f"{n} new {group} scatterers but {free} free boxes of "
                                   f"{self.sizes[group]}; raise the pool's capacity")
                self.grow({group: 2 * n - free})
        wanted = {}
        for b in bodies:
            if b.key not in self.used:
                self.used[b.key] = (b.group, self.free[b.group].pop())
            wanted[self.used[b.key]] = (tuple(b.center), float(b.yaw), tuple(b.size), tuple(b.velocity))
        return wanted

    def objects(self) -> list:
        """The pool's scene objects: one mesh per group, holding all its boxes."""
        return list(self.meshes.values())

    def parked(self, obj) -> bool:
        """Whether every box of the mesh ``obj`` of this pool is parked (it shows no body now)."""
        group = self._group_of_mesh[id(obj)]
        return all(self.state.get((group, i)) is None for i in range(self.sizes[group]))

    def boxes(self, obj) -> np.ndarray:
        """The axis-aligned bounds (m, 2, 3) of the boxes the mesh ``obj`` shows now (not
        the parked ones)."""
        group = self._group_of_mesh[id(obj)]
        out = [box_vertices(s[0], s[1], s[2]) for i in range(self.sizes[group])
               if (s := self.state.get((group, i))) is not None]
        return np.array([[v.min(axis=0), v.max(axis=0)] for v in out]).reshape(-1, 2, 3)

    def velocity_of(self, key: str) -> np.ndarray | None:
        """The velocity of the box showing ``key`` (m/s), or None."""
        if key not in self.used:
            return None
        group, i = self.used[key]
        return self.velocities[group][i].copy()

    def vertices_of(self, key: str) -> np.ndarray | None:
        """The eight corners (8, 3) of the box showing ``key``, as the scene has them."""
        if key not in self.used:
            return None
        group, i = self.used[key]
        return vertex_positions(self.scene, self.meshes[group]).reshape(-1, 8, 3)[i]

    def key_at(self, object_id: int, primitive: int) -> str | None:
        """Whose box the hit on object ``object_id``, triangle ``primitive`` is (None: not
        one of this pool's boxes, or a parked one)."""
        for group, obj in self.meshes.items():
            if int(obj.object_id) == int(object_id):
                slot = (group, int(primitive) // len(BOX_FACES))
                return next((k for k, s in self.used.items() if s == slot), None)
        return None

    def velocity_at(self, object_ids: np.ndarray, primitives: np.ndarray) -> np.ndarray:
        """The velocity (..., 3) of the box each hit (object id, triangle) is on; zero for hits
        on anything else."""
        out = np.zeros((*np.shape(object_ids), 3))
        slot = np.asarray(primitives).astype(np.int64) // len(BOX_FACES)
        for group, obj in self.meshes.items():
            # (a primitive beyond the boxes: none of them)
            on = (np.asarray(object_ids) == int(obj.object_id)) & (slot < self.sizes[group])
            if on.any():
                out[on] = self.velocities[group][slot[on]]
        return out


_PARKED = box_vertices((0.0, 0.0, PARK_Z), 0.0, (PARK_SIZE,) * 3)


def box_doppler_hz(pools: list[ScattererPool], interactions: np.ndarray, objects: np.ndarray,
                   primitives: np.ndarray, vertices: np.ndarray, sources: np.ndarray, targets: np.ndarray,
                   wavelength: float) -> np.ndarray:
    """The Doppler shift (Hz) that the pools' boxes add to each path, as Sionna RT computes
    it for a moving object: at each interaction on a box of velocity v, (k_o − k_i)·v/λ, with
    k_i and k_o the unit directions of the incoming and outgoing segments.

    Arrays as Sionna's ``Paths`` give them with a synthetic array: ``interactions``,
    ``objects`` and ``primitives`` (depth, rx, tx, paths), ``vertices`` (depth, rx, tx,
    paths, 3), ``sources`` (tx, 3), ``targets`` (rx, 3). Returns (rx, tx, paths)."""
    interactions = np.asarray(interactions)
    depth = interactions.shape[0]
    vertices = np.asarray(vertices, dtype=float)
    out = np.zeros(interactions.shape[1:])
    if depth == 0 or out.size == 0:
        return out
    velocity = np.zeros(vertices.shape)
    for pool in pools:
        velocity += pool.velocity_at(objects, primitives)
    src = np.broadcast_to(np.asarray(sources, dtype=float)[None, :, None, :], vertices.shape[1:])
    tgt = np.broadcast_to(np.asarray(targets, dtype=float)[:, None, None, :], vertices.shape[1:])
    for d in range(depth):
        here = interactions[d] != 0
        if not (here & np.any(velocity[d] != 0, axis=-1)).any():
            continue
        prev = src if d == 0 else vertices[d - 1]
        last = ~(interactions[d + 1] != 0) if d + 1 < depth else np.ones(here.shape, bool)
        nxt = np.where(last[..., None], tgt, vertices[d + 1] if d + 1 < depth else tgt)
        k_i = vertices[d] - prev
        k_o = nxt - vertices[d]
        k_i /= np.maximum(np.linalg.norm(k_i, axis=-1, keepdims=True), 1e-12)
        k_o /= np.maximum(np.linalg.norm(k_o, axis=-1, keepdims=True), 1e-12)
        out += np.where(here, np.einsum("...i,...i->...", k_o - k_i, velocity[d]), 0.0) / wavelength
    return out


def update_pools(updates: list[tuple[ScattererPool, list[Body]]], grow: bool = False) -> list[int]:
    """:meth:`ScattererPool.update` for several pools of one scene, with one update of the
    scene (one acceleration-structure rebuild, about 20 ms in the osm-city scene) for all
    of them. Every pool is assigned (and grown, which edits the scene) before any vertex is
    written. Returns how many boxes of each pool changed."""
    t0 = time.perf_counter()
    if len({id(pool.scene) for pool, _ in updates}) > 1:
        raise ValueError("update_pools: the pools belong to different scenes")
    wanted = [pool._assign(bodies, grow) for pool, bodies in updates]
    changed = [pool._stage(w) for (pool, _), w in zip(updates, wanted, strict=True)]
    if any(changed):
        geometry_changed(updates[0][0].scene)
    elapsed = time.perf_counter() - t0
    for (pool, _), n in zip(updates, changed, strict=True):
        pool.last_update_s, pool.last_changed = elapsed, n
    return changed
