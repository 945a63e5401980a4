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

    def __init__(self, scene, capacity: dict[str, int], materials: dict[str, object], prefix: str = "scatterer"):
        import mitsuba as mi
        import sionna.rt as rt

        self.mi = mi
        self.scene = scene
        self.slots: dict[str, list] = {}  # group -> [SceneObject]
        self.free: dict[str, list[int]] = {}
        self.used: dict[str, tuple[str, int]] = {}  # key -> (group, slot)
        self.state: dict[tuple[str, int], tuple] = {}  # what each slot shows now
        objects = []
        for group, n in capacity.items():
            self.slots[group] = []
            for i in range(n):
                mesh = mi.Mesh(f"{prefix}-{group}-{i}", vertex_count=8, face_count=len(BOX_FACES),
                               has_vertex_normals=False, has_vertex_texcoords=False)
                p = mi.traverse(mesh)
                p["vertex_positions"] = mi.Float(self._parked(group, i).ravel().astype(np.float32))
                p["faces"] = mi.UInt32(BOX_FACES.ravel())
                p.update()
                obj = rt.SceneObject(mi_mesh=mesh, name=f"{prefix}-{group}-{i}", radio_material=materials[group])
                obj.velocity = [0.0, 0.0, 0.0]  # creates the attribute now: no recompile later
                self.slots[group].append(obj)
                objects.append(obj)
            self.free[group] = list(range(n - 1, -1, -1))  # pop() gives slot 0 first
        if objects:
            scene.edit(add=objects)
        self.last_update_s = 0.0
        self.last_changed = 0

    @staticmethod
    def _parked(group: str, i: int) -> np.ndarray:
        return box_vertices((0.0, 0.0, PARK_Z), 0.0, (PARK_SIZE,) * 3)

    @property
    def capacity(self) -> dict[str, int]:
        return {g: len(s) for g, s in self.slots.items()}

    def update(self, bodies: list[Body]) -> int:
        """Shows exactly ``bodies`` (others parked); returns how many boxes changed.
        Raises :class:`PoolFull` if a group has more bodies than boxes."""
        t0 = time.perf_counter()
        mi = self.mi
        present = {b.key for b in bodies}
        for key in [k for k in self.used if k not in present]:
            group, slot = self.used.pop(key)
            self.free[group].append(slot)
        wanted: dict[tuple[str, int], tuple] = {}
        for b in bodies:
            if b.key not in self.used:
                if b.group not in self.free:
                    raise KeyError(f"no scatterer pool for group {b.group!r} (pools: {', '.join(self.slots)})")
                if not self.free[b.group]:
                    raise PoolFull(f"more than {len(self.slots[b.group])} {b.group} scatterers at once; "
                                   f"raise the pool's capacity")
                self.used[b.key] = (b.group, self.free[b.group].pop())
            wanted[self.used[b.key]] = (tuple(b.center), float(b.yaw), tuple(b.size), tuple(b.velocity))
        params = self.scene.mi_scene_params
        changed = 0
        for group, objs in self.slots.items():
            for i, obj in enumerate(objs):
                state = wanted.get((group, i))
                if self.state.get((group, i)) == state:
                    continue
                self.state[(group, i)] = state
                if state is None:
                    verts, vel = self._parked(group, i), (0.0, 0.0, 0.0)
                else:
                    verts, vel = box_vertices(state[0], state[1], state[2]), state[3]
                params[obj.mi_mesh.id() + ".vertex_positions"] = mi.Float(verts.ravel().astype(np.float32))
                if tuple(np.asarray(obj.velocity).ravel()) != tuple(np.float32(vel)):
                    obj.velocity = [float(v) for v in vel]
                changed += 1
        if changed:
            params.update()
            self.scene.scene_geometry_updated()
        self.last_update_s = time.perf_counter() - t0
        self.last_changed = changed
        return changed

    def slot_of(self, key: str):
        """The scene object showing ``key``, or None."""
        if key not in self.used:
            return None
        group, i = self.used[key]
        return self.slots[group][i]
