"""The ray-traced scene: loading it, the objects that move in it, and the one place that
writes its vertex positions.

* :func:`build_scene`: the one way a module gets a scene to trace in (loaded by
  :func:`scene_path` / :func:`load_scene`: a shipped scene by name, a Mitsuba XML file, or
  free space; with its carrier, arrays and transmitters), and what a module adds to it
  (:func:`receiver`, :func:`scene_object`, :func:`itu_material`);
* :class:`MovingObjects`: the objects a caller moves from solve to solve (UAV bodies,
  vehicle boxes) that the shoot cache handles on top of its recorded bounces, and the
  :func:`geometry_fingerprint` that leaves them out;
* vertex positions: :func:`write_vertex_positions` (then :func:`geometry_changed`),
  :func:`vertex_positions`, and :func:`objects_out_of_the_way`;
* which shapes a ray meets first: :func:`first_hits`, :func:`shape_table`, :func:`on_shapes`;
  where and on what surface (a range sensor's hits): :func:`surface_hits`;
  and which points are outdoors: :func:`open_sky`.

Sionna RT's public scene API (``load_scene``, ``SceneObject``, ``Scene.edit``) is used as
documented; Mitsuba's scene parameters (``mi_scene_params``) only here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from caviar_plugins.assets import SCENES
from caviar_plugins.rt.drjit_setup import aligned_array, configure_drjit, jit, set_thread_count


def scene_path(name: str, base: pathlib.Path | None = None) -> pathlib.Path | None:
    """A shipped scene by name (``central_park``), or a path to a Mitsuba XML file.
    ``empty`` gives None: free space."""
    if name == "empty":
        return None
    shipped = SCENES / name / f"{name}.xml"
    if shipped.exists():
        return shipped
    p = pathlib.Path(name)
    if not p.is_absolute() and base is not None:
        p = base / p
    if not p.exists():
        known = ", ".join(sorted(d.name for d in SCENES.iterdir() if d.is_dir()))
        raise FileNotFoundError(f"scene '{name}': neither a shipped scene ({known}, empty) nor an existing file")
    return p


def load_scene(name: str, base: pathlib.Path | None = None, merge_shapes: bool = True) -> Any:
    """Sionna RT's scene for :func:`scene_path` (``empty``: free space). Sionna merges the
    shapes of one material into one object by default (faster to trace);
    ``merge_shapes=False`` keeps each shape an object of its own name (a sensor that says
    what it hit)."""
    rt = sionna_rt()
    path = scene_path(name, base)
    return rt.load_scene(str(path), merge_shapes=merge_shapes) if path else rt.load_scene()


@dataclasses.dataclass(frozen=True)
class AntennaArray:
    """A planar array (Sionna's ``PlanarArray``): ``rows`` along z × ``cols`` along y,
    ``spacing`` in wavelengths on both axes, each element's ``pattern`` (``iso``, ``dipole``,
    ``tr38901``) and ``polarization`` (``V``, ``H``, ``VH``, ``cross``)."""

    rows: int = 1
    cols: int = 1
    spacing: float = 0.5
    pattern: str = "iso"
    polarization: str = "V"


@dataclasses.dataclass(frozen=True)
class Emitter:
    """A transmitter: its name, position (m) and orientation (yaw, pitch, roll in radians)."""

    name: str
    position: Sequence[float]
    orientation: Sequence[float] = (0.0, 0.0, 0.0)


def build_scene(name: str, base: pathlib.Path | None = None, *, frequency_hz: float | None = None,
                tx_array: AntennaArray | None = None, rx_array: AntennaArray | None = None,
                transmitters: Sequence[Emitter] = (), threads: int = 0, merge_shapes: bool = True) -> Any:
    """The one way a module gets a scene to trace in: :func:`load_scene` (a shipped scene,
    a Mitsuba XML file or ``empty``), Dr.Jit's CPU ``threads`` (0: all cores), the carrier,
    the arrays of the transmitters and receivers (:class:`AntennaArray`) and the
    transmitters. Receivers, bodies and materials are added by the caller
    (:func:`receiver`, :func:`scene_object`, :func:`itu_material`)."""
    set_thread_count(threads)
    scene = load_scene(name, base, merge_shapes=merge_shapes)
    if frequency_hz is not None:
        scene.frequency = float(frequency_hz)
    if tx_array is not None:
        scene.tx_array = planar_array(tx_array)
    if rx_array is not None:
        scene.rx_array = planar_array(rx_array)
    rt = sionna_rt()
    for e in transmitters:
        scene.add(rt.Transmitter(e.name, position=[float(v) for v in e.position],
                                 orientation=[float(v) for v in e.orientation]))
    return scene


def sionna_rt() -> Any:
    """Sionna RT, with Dr.Jit set up first (:func:`configure_drjit`)."""
    configure_drjit()
    import sionna.rt as rt

    return rt


def planar_array(spec: AntennaArray) -> Any:
    """Sionna's ``PlanarArray`` for ``spec``."""
    return sionna_rt().PlanarArray(num_rows=spec.rows, num_cols=spec.cols, vertical_spacing=spec.spacing,
                                   horizontal_spacing=spec.spacing, pattern=spec.pattern,
                                   polarization=spec.polarization)


def receiver(name: str, position: Sequence[float], orientation: Sequence[float] | None = None) -> Any:
    """A Sionna ``Receiver`` (not yet in a scene: ``scene.add`` it)."""
    rt = sionna_rt()
    if orientation is None:
        return rt.Receiver(name, position=[float(v) for v in position])
    return rt.Receiver(name, position=[float(v) for v in position], orientation=[float(v) for v in orientation])


def itu_material(name: str, itu_type: str, thickness: float) -> Any:
    """An ITU-R P.2040 radio material (Sionna's ``ITURadioMaterial``): ``itu_type`` such as
    ``metal`` or ``concrete``, ``thickness`` in metres."""
    return sionna_rt().ITURadioMaterial(name, itu_type, thickness=thickness)


def scene_object(fname: str | pathlib.Path, name: str, material: Any) -> Any:
    """A Sionna ``SceneObject`` from a mesh file (not yet in a scene: ``scene.edit(add=…)``)."""
    return sionna_rt().SceneObject(fname=str(fname), name=name, radio_material=material)


def bounding_box(obj) -> np.ndarray:
    """A scene object's bounding box as bounds (1, 2, 3)."""
    box = obj.mi_mesh.bbox()
    return np.array([[np.array(box.min), np.array(box.max)]], dtype=float)


# --- the objects that move ----------------------------------------------------------------

class MovingObjects:
    """The objects of ``scene`` that move from solve to solve, for the shoot cache: ``bodies``
    (a UAV's body by its key) and the objects :meth:`declare` names (vehicles, persons).
    ``enabled = False``: none counts as moving (every move is a new geometry).
    ``rays_per_object``: the rays the cache aims at each body of one (0: Sionna's own)."""

    def __init__(self, scene: Any, enabled: bool = True, rays_per_object: int = 4096):
        self.scene = scene
        self.enabled = enabled
        self.rays_per_object = rays_per_object
        self.bodies: dict[str, Any] = {}
        self._away: set[int] = set()  # ids of bodies put out of the way (no rays aimed at them)
        # id -> (object, is it away?, its bodies' bounds)
        self._declared: dict[int, tuple[Any, Callable[[Any], bool] | None, Callable[[Any], Any] | None]] = {}

    def present(self) -> list[Any]:
        """The moving objects now in the scene (none when not ``enabled``)."""
        if not self.enabled:
            return []
        return list(self.bodies.values()) + [entry[0] for entry in self._declared.values() if self.in_scene(entry[0])]

    def in_scene(self, obj: Any) -> bool:
        """Whether a declared object is still in the scene (not, e.g., a pool's mesh since
        replaced by a larger one)."""
        return self.scene.objects.get(obj.name) is obj

    def declare(self, objects: Sequence[Any], away: Callable[[Any], bool] | None = None,
                boxes: Callable[[Any], np.ndarray] | None = None) -> None:
        """Declares objects that a caller moves. ``away(obj)``: whether an object is out of
        the scene for now (parked; no rays are aimed at it). ``boxes(obj)``: the bounds
        (m, 2, 3) of each of its separate bodies (a pool's mesh of boxes); without it, its
        bounding box. Declaring an object again does nothing."""
        for key in [k for k, entry in self._declared.items() if not self.in_scene(entry[0])]:
            del self._declared[key]
        for obj in objects:
            self._declared.setdefault(id(obj), (obj, away, boxes))

    def set_away(self, body: Any, away: bool) -> None:
        """Whether a UAV body is out of the way for now (parked: no rays are aimed at it)."""
        if away:
            self._away.add(id(body))
        else:
            self._away.discard(id(body))

    def rays_at(self, obj: Any) -> int | None:
        """Rays the shoot cache aims at each body of ``obj`` (0: none, it is away; None: as
        dense as Sionna's own)."""
        if id(obj) in self._away:
            return 0
        entry = self._declared.get(id(obj))
        away = entry[1] if entry is not None else None
        if away is not None and away(obj):
            return 0
        return self.rays_per_object or None

    def boxes_of(self, obj: Any) -> np.ndarray:
        """The bounds (m, 2, 3) of ``obj``'s bodies."""
        entry = self._declared.get(id(obj))
        if entry is not None and entry[2] is not None:
            return np.asarray(entry[2](obj), dtype=float).reshape(-1, 2, 3)
        return bounding_box(obj)

    def fingerprint(self) -> tuple:
        """:func:`geometry_fingerprint` of the scene without the objects that move."""
        return geometry_fingerprint(self.scene, self.present())


def geometry_fingerprint(scene: Any, leave_out: Sequence[Any] = ()) -> tuple:
    """What the rays' bounces depend on besides the transmitters and the solver's settings:
    every object's name, position, orientation, scale and material (but ``leave_out``),
    every material's parameters and the frequency (the shoot cache's key)."""
    moving = {id(obj) for obj in leave_out}
    objects = tuple((name, *(tuple(np.asarray(getattr(obj, a), dtype=float).ravel().tolist())
                             for a in ("position", "orientation", "scaling")), obj.radio_material.name)
                    for name, obj in scene.objects.items() if id(obj) not in moving)
    materials = []
    for name, mat in scene.radio_materials.items():
        values: list[Any] = []
        for a in ("relative_permittivity", "conductivity", "scattering_coefficient", "xpd_coefficient", "thickness"):
            v = getattr(mat, a, None)
            values.append(None if v is None else tuple(np.asarray(v, dtype=float).ravel().tolist()))
        pattern = getattr(mat, "scattering_pattern", None)
        values.append(type(pattern).__name__)
        for a in ("alpha_r", "alpha_i", "lambda_"):
            v = getattr(pattern, a, None)
            if v is not None:
                values.append(tuple(np.asarray(v, dtype=float).ravel().tolist()))
        materials.append((name, type(mat).__name__, *values))
    return objects, tuple(materials), float(np.asarray(scene.frequency).ravel()[0])


# --- vertex positions ---------------------------------------------------------------------

def _vertex_key(obj: Any) -> str:
    return obj.mi_mesh.id() + ".vertex_positions"


def write_vertex_positions(scene: Any, obj: Any, vertices: Sequence[float]) -> None:
    """Writes a scene object's vertex positions (flat x, y, z, ...) into the scene's
    parameters, without rebuilding the acceleration structure: call
    :func:`geometry_changed` once after every write of a step. A Python list is copied by
    Dr.Jit into memory of its own; numpy memory is taken as it is, and a kernel is
    compiled anew for each alignment."""
    _, mi = jit()
    scene.mi_scene_params[_vertex_key(obj)] = mi.Float(
        vertices if isinstance(vertices, list) else np.asarray(vertices, dtype=float).ravel().tolist())


def geometry_changed(scene: Any) -> None:
    """Rebuilds the acceleration structure after :func:`write_vertex_positions` and tells
    Sionna the geometry changed."""
    scene.mi_scene_params.update()
    scene.scene_geometry_updated()


def move_objects(scene: Any, moves: Sequence[tuple[Any, Any]]) -> None:
    """Moves scene objects so that each one's centre (of its bounding box, Sionna's
    ``position``) is at its new position. Sionna's ``position`` setter rebuilds the
    acceleration structure for each object (about 12 ms each in the SAR scene on the CPU);
    several objects are moved here in one rebuild, with the setter's float32 arithmetic
    (vertices + (new position − centre)), so the vertices are the setter's bit for bit.
    ``moves``: (object, position (3,)). One object goes through the setter itself."""
    if len(moves) == 1:
        obj, position = moves[0]
        obj.position = np.asarray(position, dtype=float).tolist()
        return
    for obj, position in moves:
        v = vertex_positions(scene, obj).astype(np.float32)
        centre = (v.min(axis=0) + v.max(axis=0)) * np.float32(0.5)
        shift = np.asarray(position, dtype=np.float64).astype(np.float32) - centre
        write_vertex_positions(scene, obj, (v + shift).ravel().tolist())
    if moves:
        geometry_changed(scene)


def vertex_positions(scene: Any, obj: Any) -> np.ndarray:
    """A scene object's vertex positions as the scene has them, (vertices, 3)."""
    return np.array(scene.mi_scene_params[_vertex_key(obj)]).reshape(-1, 3)


OUT_OF_THE_WAY_M = 1.0e4
"""How far below the scene :func:`objects_out_of_the_way` moves objects."""


@contextlib.contextmanager
def objects_out_of_the_way(scene: Any, objects: Sequence[Any]) -> Iterator[None]:
    """Moves ``objects`` (Sionna ``SceneObject``s of ``scene``) :data:`OUT_OF_THE_WAY_M`
    below the scene while the block runs, in one scene update, and then puts their vertex
    buffers back bit for bit (another update): the geometry afterwards is exactly the one
    before."""
    if not objects:
        yield
        return
    dr, mi = jit()
    params = scene.mi_scene_params
    keys = [_vertex_key(obj) for obj in objects]
    saved = [dr.copy(params[k]) for k in keys]
    for key, vertices in zip(keys, saved, strict=True):
        params[key] = dr.ravel(dr.unravel(mi.Point3f, vertices) + mi.Point3f(0.0, 0.0, -OUT_OF_THE_WAY_M))
    params.update()
    try:
        yield
    finally:
        for key, vertices in zip(keys, saved, strict=True):
            params[key] = vertices
        params.update()


# --- what a ray meets first ---------------------------------------------------------------

def first_hits(scene: Any, origins: np.ndarray, directions: np.ndarray,
               max_distance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For rays from ``origins`` (n, 3) along unit ``directions`` (n, 3), up to
    ``max_distance`` (n; None: no limit): whether each hits anything, the Mitsuba shape id
    (a scene object's ``object_id``) and the triangle it hits first. Only which shape is hit
    is computed (the preliminary intersection: no surface interaction, no call into every
    shape of the scene)."""
    dr, mi = jit()
    origins, directions = np.asarray(origins, dtype=float), np.asarray(directions, dtype=float)
    # (Arrays from Python lists: Dr.Jit copies them into memory of its own.)
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(origins[:, j].tolist()) for j in range(3))),
                   mi.Vector3f(*(mi.Float(directions[:, j].tolist()) for j in range(3))))
    if max_distance is not None:
        ray.maxt = mi.Float(np.asarray(max_distance, dtype=float).tolist())
    si = scene.mi_scene.ray_intersect_preliminary(ray)
    return (np.array(si.is_valid(), dtype=bool), np.array(dr.reinterpret_array(mi.UInt32, si.shape)),
            np.array(si.prim_index))


def surface_hits(scene: Any, origins: np.ndarray, directions: np.ndarray,
                 max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For rays from ``origins`` (n, 3) along unit ``directions`` (n, 3), float32, up to
    ``max_distance``: whether each hits anything, the distance to the hit, the Mitsuba
    shape id hit (0: none), the surface normal there (n, 3) and the triangle. What a
    range sensor needs (:mod:`caviar_plugins.lidar`): a surface interaction without the
    shapes' own computations (``RayFlags.Minimal``), in one evaluation."""
    dr, mi = jit()
    o = np.asarray(origins, dtype=np.float32)
    d = np.asarray(directions, dtype=np.float32)
    ray = mi.Ray3f(mi.Point3f(*(aligned_array(mi.Float, np.ascontiguousarray(o[:, k])) for k in range(3))),
                   mi.Vector3f(*(aligned_array(mi.Float, np.ascontiguousarray(d[:, k])) for k in range(3))))
    ray.maxt = mi.Float(float(max_distance))
    si = scene.mi_scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
    hit = si.is_valid()
    t = dr.select(hit, si.t, 0.0)
    shape = dr.select(hit, dr.reinterpret_array(mi.UInt32, si.shape), 0)
    n = si.n
    dr.eval(t, shape, n, si.prim_index)
    normal = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1)
    return (np.array(hit, dtype=bool), np.array(t, dtype=float), np.array(shape, dtype=np.int64), normal,
            np.array(si.prim_index, dtype=np.int64))


def open_sky(scene: Any, points: np.ndarray) -> np.ndarray:
    """Whether each point (n, 3) has open sky above it: a ray straight up meets nothing.
    False inside a building (its roof is above), under a bridge or an overhang."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    up = np.broadcast_to([0.0, 0.0, 1.0], points.shape)
    return ~first_hits(scene, points, up)[0]


def shape_table(scene, objects) -> Any:
    """A Dr.Jit Bool array indexed by Mitsuba shape id (a hit's ``si.shape`` as UInt32):
    true for the shapes of ``objects``, false for every other shape and for "no shape" (0).
    One gather per hit then tells whether it is on a moving object, whatever their number."""
    _, mi = jit()
    ids = [int(o.object_id) for o in objects]
    size = max([int(o.object_id) for o in scene.objects.values()] + ids) + 2  # the last entry: any other id
    table = np.zeros(size, dtype=bool)
    table[ids] = True
    return aligned_array(mi.Bool, table)


def on_shapes(table, si) -> Any:
    """Whether each hit of ``si`` (a surface or preliminary intersection) lies on a shape that
    ``table`` (:func:`shape_table`) marks."""
    dr, mi = jit()
    ids = dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), dr.width(table) - 1)
    return si.is_valid() & dr.gather(mi.Bool, table, ids, si.is_valid())
