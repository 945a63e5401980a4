"""Moving scatterers in a Sionna RT scene: a pool of box meshes that vehicles and
pedestrians borrow while they are in the scene.

The pool is added to the scene once (one ``scene.edit``, one kernel recompile). After
that an entity arriving takes a free box, one leaving gives it back (parked 1 km below
the ground, shrunk to 1 cm), and every step all boxes that moved get their eight
vertices rewritten in the Mitsuba scene parameters and the acceleration structure is
rebuilt once (one ``params.update()``): the scene is never reloaded and, since the
number of shapes and vertices does not change, the path solver's kernels are reused.

Each box also carries its velocity (Sionna RT's per-object ``velocity``), so paths
reflected by a moving vehicle get its Doppler shift.

Nothing of caviar here: :class:`ScattererPool` takes a ``sionna.rt.Scene``.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

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
    ``scene`` in one edit."""

    def __init__(self, scene, capacity: dict[str, int], materials: dict[str, object], prefix: str = "scatterer",
                 edits: list[tuple[str, dict[str, int]]] | None = None):
        import mitsuba as mi
        import sionna.rt as rt

        self.mi = mi
        self.scene = scene
        self.slots: dict[str, list] = {}  # group -> [SceneObject]
        self._slot_of_object: dict[int, tuple[str, int]] = {}  # id(SceneObject) -> (group, slot)
        self.free: dict[str, list[int]] = {}
        self.used: dict[str, tuple[str, int]] = {}  # key -> (group, slot)
        self.state: dict[tuple[str, int], tuple | None] = {}  # what each slot shows now
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
        at the next solve)."""
        mi = self.mi
        objects = []
        for group, n in more.items():
            slots = self.slots.setdefault(group, [])
            free = self.free.setdefault(group, [])
            start = len(slots)
            for i in range(start, start + n):
                mesh = mi.Mesh(f"{self.prefix}-{group}-{i}", vertex_count=8, face_count=len(BOX_FACES),
                               has_vertex_normals=False, has_vertex_texcoords=False)
                p = mi.traverse(mesh)
                p["vertex_positions"] = mi.Float(self._parked(group, i).ravel().astype(np.float32))
                p["faces"] = mi.UInt32(BOX_FACES.ravel())
                p.update()
                obj = self.rt.SceneObject(mi_mesh=mesh, name=f"{self.prefix}-{group}-{i}",
                                          radio_material=self.materials[group])
                obj.velocity = [0.0, 0.0, 0.0]  # creates the attribute now: no recompile later
                slots.append(obj)
                self._slot_of_object[id(obj)] = (group, i)
                objects.append(obj)
            free[:0] = list(range(start + n - 1, start - 1, -1))  # pop() gives the lowest slot first
        if objects:
            self.scene.edit(add=objects)
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
        params = self.scene.mi_scene_params
        for (group, i), state in snapshot["state"].items():
            if self.state.get((group, i)) != state:
                self.state[(group, i)] = state
                self._show(params, group, i, self.slots[group][i], state)
        params.update()
        self.scene.scene_geometry_updated()

    @staticmethod
    def _parked(group: str, i: int) -> np.ndarray:
        return box_vertices((0.0, 0.0, PARK_Z), 0.0, (PARK_SIZE,) * 3)

    @property
    def capacity(self) -> dict[str, int]:
        return {g: len(s) for g, s in self.slots.items()}

    def update(self, bodies: list[Body], grow: bool = False) -> int:
        """Shows exactly ``bodies`` (others parked); returns how many boxes changed.
        A group with more bodies than boxes raises :class:`PoolFull`, or with ``grow``
        gets twice the boxes it needs (one scene edit, one recompile)."""
        return update_pools([(self, bodies)], grow)[0]

    def _stage(self, wanted: dict[tuple[str, int], tuple]) -> int:
        """Writes the vertices of the boxes whose state changed into the scene's parameters
        (without updating the scene); returns how many changed."""
        params = self.scene.mi_scene_params
        changed = 0
        for group, objs in self.slots.items():
            for i, obj in enumerate(objs):
                state = wanted.get((group, i))
                if self.state.get((group, i)) != state:
                    self.state[(group, i)] = state
                    self._show(params, group, i, obj, state)
                    changed += 1
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
            if group not in self.slots and not grow:
                raise KeyError(f"no scatterer pool for group {group!r} (pools: {', '.join(self.slots)})")
            free = len(self.free.get(group, []))
            if n > free:
                if not grow:
                    raise PoolFull(f"{n} new {group} scatterers but {free} free boxes of "
                                   f"{len(self.slots[group])}; raise the pool's capacity")
                self.grow({group: 2 * n - free})
        wanted = {}
        for b in bodies:
            if b.key not in self.used:
                self.used[b.key] = (b.group, self.free[b.group].pop())
            wanted[self.used[b.key]] = (tuple(b.center), float(b.yaw), tuple(b.size), tuple(b.velocity))
        return wanted

    def _show(self, params, group: str, i: int, obj, state) -> None:
        if state is None:
            verts, vel = self._parked(group, i), (0.0, 0.0, 0.0)
        else:
            verts, vel = box_vertices(state[0], state[1], state[2]), state[3]
        # (From a Python list: Dr.Jit copies it into memory of its own; a numpy array's memory is
        # taken as it is, and its alignment varies: about 10 % of the update, measured.)
        params[obj.mi_mesh.id() + ".vertex_positions"] = self.mi.Float(verts.ravel().tolist())
        if tuple(np.asarray(obj.velocity).ravel()) != tuple(np.asarray(vel, dtype=np.float32)):
            obj.velocity = [float(v) for v in vel]

    def objects(self) -> list:
        """Every box of the pool (scene objects), parked or not."""
        return [obj for objs in self.slots.values() for obj in objs]

    def parked(self, obj) -> bool:
        """Whether the box ``obj`` of this pool is parked (shows no body now)."""
        return self.state.get(self._slot_of_object[id(obj)]) is None

    def slot_of(self, key: str):
        """The scene object showing ``key``, or None."""
        if key not in self.used:
            return None
        group, i = self.used[key]
        return self.slots[group][i]


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
        scene = updates[0][0].scene
        scene.mi_scene_params.update()
        scene.scene_geometry_updated()
    elapsed = time.perf_counter() - t0
    for (pool, _), n in zip(updates, changed, strict=True):
        pool.last_update_s, pool.last_changed = elapsed, n
    return changed
