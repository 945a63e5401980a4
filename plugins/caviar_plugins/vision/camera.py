"""UAV camera images rendered with Mitsuba 3 from the same 3D scene as the radio.

A frame is cheap because it is not path traced: one pass of Mitsuba's AOV
integrator gives each sample's shape and normal; the shape's colour and a
sun-and-sky Lambert term are applied in numpy, and 2 × 2 samples per pixel are
averaged. 160 × 120 takes about 10 ms on 2 CPU cores (about 5 ms per view when a
step's views are rendered together, :meth:`VisualScene.render_many`) (the default path tracer:
about 2.6 s at 320 × 240, 16 spp). The shape index also gives exact person masks:
the labels for training and evaluating the detector.

The renderer runs in whatever Mitsuba variant is active, the radio's included:
switching variants costs about 70 ms each way (Mitsuba reloads Python modules),
so the camera never switches.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import warnings
from typing import Any

import numpy as np

import caviar
from caviar_plugins.assets import DATA
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.rt.drjit_setup import mitsuba
from caviar_plugins.schema import CAMERA, POSITIONS, every_ue, per_ue, read_position
from caviar_plugins.vision.shading import daylight, facing, in_shadow, shade, to_srgb8, vary_albedo

RENDERERS = ("flat", "shaded")
CLOTHES = [(0.95, 0.35, 0.05), (0.85, 0.08, 0.08), (0.95, 0.85, 0.1), (0.1, 0.25, 0.85), (0.55, 0.1, 0.6)]
SKIN = (0.8, 0.6, 0.45)
SKY = (0.6, 0.75, 0.95)


def shape_ids(scene) -> tuple[np.ndarray, list[str]]:
    """Each shape's registry id (its pointer as an integer, as a ``shape_index`` AOV or a hit's
    ``shape`` gives it) and its name, in the scene's order."""
    import drjit as dr

    mi = mitsuba()
    ids = np.array(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()), dtype=np.int64)
    return ids, [sh.id() for sh in scene.shapes()]


def default_targets(count: int = 5, offset_m: float = 3.0) -> list[list[float]]:
    """The paper's 5 rescue targets: evenly along the scene-frame route, 3 m to its side."""
    path = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    out = []
    for s in np.linspace(0.12, 0.92, count) * path.length:
        p, q = path.at(s), path.at(s + 1.0)
        side = np.array([-(q - p)[1], (q - p)[0]])
        side /= np.linalg.norm(side) or 1.0
        out.append([round(float(p[0] + offset_m * side[0]), 2), round(float(p[1] + offset_m * side[1]), 2)])
    return out


@dataclasses.dataclass
class VisualConfig:
    scene: str = "central_park"
    targets: list[list[float]] = dataclasses.field(default_factory=default_targets)
    """Persons lying on the ground, [x, y] each."""
    distractors: int = 60
    """Bushes and rocks scattered along the route (seeded)."""
    width: int = 160
    height: int = 120
    fov_deg: float = 70.0
    """Horizontal field of view."""
    supersample: int = 2
    """Samples per pixel along each axis (averaged: anti-aliasing)."""
    render: str = "flat"
    """``flat``: each shape's colour under a fixed Lambert term (no shadows), the loop's
    renderer since the start; ``shaded``: the light of the detector's training frames
    (:mod:`~caviar_plugins.vision.shading`): a sun with cast shadows, a sky term, an
    exposure and the ground's albedo noise."""
    sun_elevation_deg: float = 45.0
    """shaded: the sun's elevation above the horizon (the training frames: 15° to 75°)."""
    sun_azimuth_deg: float = 135.0
    """shaded: the sun's azimuth, counter-clockwise from x (east)."""
    sky: float = 0.35
    """shaded: the sky term (the training frames: 0.25 to 0.5)."""
    exposure: float = 1.0
    """shaded: the exposure (the training frames: 0.75 to 1.25)."""

    def __post_init__(self):
        if self.render not in RENDERERS:
            raise ValueError(f"render: expected one of {list(RENDERERS)}, got {self.render!r}")
        if not 0.0 < self.sun_elevation_deg <= 90.0:
            raise ValueError(f"sun_elevation_deg: expected degrees in (0, 90], got {self.sun_elevation_deg!r}")
        if not 0.0 <= self.sky <= 1.0 or not 0.0 < self.exposure <= 4.0:
            key = "sky" if not 0.0 <= self.sky <= 1.0 else "exposure"
            raise ValueError(f"{key}: expected sky in [0, 1] and exposure in (0, 4], got {getattr(self, key)!r}")

    def light(self) -> dict:
        """The shaded renderer's light (:func:`~caviar_plugins.vision.shading.daylight`)."""
        return daylight(self.sun_elevation_deg, self.sun_azimuth_deg, self.sky, self.exposure)


GROUND = (0.22, 0.45, 0.16)
BUILDINGS = (0.55, 0.55, 0.6)
ROADS = (0.25, 0.25, 0.27)


def _scene_meshes(scene: str, base_dir: pathlib.Path | None, d: dict) -> dict[str, tuple[float, float, float]]:
    """Adds the static meshes of ``scene`` to the Mitsuba dict ``d``; their colours by id.

    The shipped Central Park scene, or any Mitsuba XML of PLY shapes (``scene =
    "DIR/scene.xml"``, e.g. built by ``caviar-core scene build``); the UAV's cube of the
    paper's scene is left out (the camera is on the UAV)."""
    from caviar_plugins.osm.mitsuba import scene_shapes
    from caviar_plugins.rt.scene import scene_path

    path = scene_path(scene, base_dir)
    if path is None:  # "empty": free space over a ground plane
        d["ground"] = {"type": "rectangle", "to_world": mitsuba().ScalarTransform4f().scale([5e3, 5e3, 1])}
        return {"ground": GROUND}
    colours = {}
    for sid, ply, _material in scene_shapes(path):
        if sid in ("mesh-Cube",):
            continue
        d[sid] = {"type": "ply", "filename": str(ply)}
        low = sid.lower()
        colours[sid] = GROUND if ("ground" in low or "plane" in low) else ROADS if "road" in low else BUILDINGS
    return colours


class VisualScene:
    """Buildings, ground, persons and distractors; renders nadir views."""

    def __init__(self, cfg: VisualConfig, seed: int = 0, base_dir: pathlib.Path | None = None):
        self.cfg = cfg
        rng = np.random.default_rng(seed)
        mi = self.mi = mitsuba()
        d: dict = {"type": "scene", "integrator": {"type": "aov", "aovs": "nn:sh_normal,id:shape_index"}}
        colours = _scene_meshes(cfg.scene, base_dir, d)
        for i, (x, y) in enumerate(cfg.targets):
            yaw = float(rng.uniform(0, 180))
            d[f"person{i}-body"] = {"type": "cube", "to_world": mi.ScalarTransform4f().translate([x, y, 0.15])
                                    .rotate([0, 0, 1], yaw).scale([0.8, 0.25, 0.15])}
            colours[f"person{i}-body"] = CLOTHES[i % len(CLOTHES)]
            hx, hy = x + 0.95 * math.cos(math.radians(yaw)), y + 0.95 * math.sin(math.radians(yaw))
            d[f"person{i}-head"] = {"type": "sphere", "center": [hx, hy, 0.15], "radius": 0.14}
            colours[f"person{i}-head"] = SKIN
        path = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
        for j in range(cfg.distractors):
            if cfg.scene == "central_park":  # along the paper's route
                p = path.at(rng.uniform(0, path.length)) + np.r_[rng.normal(0, 4, 2), 0]
            else:  # another scene: around the targets
                x, y = cfg.targets[j % len(cfg.targets)] if cfg.targets else (0.0, 0.0)
                p = np.r_[x, y, 0] + np.r_[rng.normal(0, 6, 2), 0]
            if rng.uniform() < 0.5:
                r = float(rng.uniform(0.4, 1.2))
                d[f"bush{j}"] = {"type": "sphere", "center": [p[0], p[1], r * 0.6], "radius": r}
                colours[f"bush{j}"] = (0.08, 0.28, 0.06)
            else:
                size = float(rng.uniform(0.2, 0.5))
                d[f"rock{j}"] = {"type": "cube", "to_world": mi.ScalarTransform4f().translate([p[0], p[1], size])
                                 .scale([size * 1.3, size, size])}
                colours[f"rock{j}"] = (0.45, 0.42, 0.38)
        self.scene = mi.load_dict(d)
        # The shape_index AOV holds each shape's registry id: a lookup table turns ids into
        # colours and person indices.
        ids, names = shape_ids(self.scene)
        size = int(ids.max()) + 1
        self.palette = np.tile(np.array(SKY, dtype=np.float32), (size, 1))
        self.person_of_id = np.full(size, -1)
        self.noisy = np.zeros(size, dtype=bool)  # ground, roads, roofs: the shaded albedo noise
        self.seed = seed
        for i, n in zip(ids, names, strict=True):
            self.palette[i] = colours[n]
            self.noisy[i] = colours[n] in (GROUND, ROADS, BUILDINGS)
            if n.startswith("person"):
                self.person_of_id[i] = int(n[len("person"):].split("-")[0])
        self._palette_dr = [mi.Float(np.ascontiguousarray(self.palette[:, ch])) for ch in range(3)]

    def render(self, position) -> np.ndarray:
        """An sRGB uint8 image (H, W, 3) seen from ``position`` straight down."""
        return self.render_labelled(position)[0]

    def render_many(self, positions, chunk: int = 64) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`render_labelled` for many positions at once, identical images.

        Instead of one ``mi.render`` per view (a sensor, a kernel launch and a film
        each), the primary rays of all views are built in one wavefront and traced with
        one ``scene.ray_intersect``. The rays are bit for bit those the AOV integrator
        traces at 1 spp: the same independent sampler (seed 0, one sample per pixel of
        the same film: the same sub-pixel offsets for every view), the sensor's own
        ``sample_ray`` for the camera-space directions (once per distinct look-at
        rotation, usually one), and the origin ``translation + d · near_t`` added in
        float32 as the sensor does. ``chunk`` views per wavefront bound the memory (64
        views of 160 × 120 at 2 × 2 supersampling: 0.46 GB more at peak, 16 views: 0.16 GB;
        50 views in one wavefront take 0.74x the time of chunks of 16)."""
        pos = np.array([[float(v) for v in p] for p in positions], dtype=np.float64).reshape(-1, 3)
        chunk = max(1, chunk)
        out: list[tuple[np.ndarray, np.ndarray]] = []
        for s in range(0, len(pos), chunk):
            if self.cfg.render == "shaded":
                lit, labels, _ = self._shaded_chunk(pos[s:s + chunk])
                assert lit is not None
                images = lit
            else:
                images, labels = self._shade_batch(*self._trace_chunk(pos[s:s + chunk]))
            out.extend(zip(images, labels, strict=True))
        return out

    def render_depth(self, positions, chunk: int = 64) -> list[tuple[np.ndarray, np.ndarray]]:
        """(image, depth) of each view: the ``shaded`` or ``flat`` image of
        :meth:`render_many` and the distance (m, float32 H × W) from the camera to what each
        pixel sees, averaged over its samples that hit something (NaN: only sky)."""
        pos = np.array([[float(v) for v in p] for p in positions], dtype=np.float64).reshape(-1, 3)
        out: list[tuple[np.ndarray, np.ndarray]] = []
        for s in range(0, len(pos), max(1, chunk)):
            shading = self.cfg.render == "shaded"
            shaded, _, depth = self._shaded_chunk(pos[s:s + max(1, chunk)], lit=shading)
            images = list(shaded) if shaded is not None else \
                [im for im, _ in self.render_many(pos[s:s + max(1, chunk)], chunk)]
            out.extend(zip(images, depth, strict=True))
        return out

    def _view_rays(self, rotation: bytes):
        """Primary rays (origin offset, direction, maxt) of a view with this look-at
        matrix (translation zeroed), cached by its rotation."""
        cache = self.__dict__.setdefault("_ray_cache", {})
        if rotation in cache:
            return cache[rotation]
        import drjit as dr

        c, mi = self.cfg, self.mi
        k = c.supersample
        w, h = c.width * k, c.height * k
        m = np.frombuffer(rotation, dtype=np.float32).reshape(4, 4).astype(float)
        sensor = mi.load_dict({
            "type": "perspective", "fov": c.fov_deg, "fov_axis": "x", "to_world": mi.ScalarTransform4f(m.tolist()),
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                     "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"},
            "sampler": {"type": "independent", "sample_count": 1},
        })
        sampler = sensor.sampler().clone()
        sampler.seed(0, w * h)
        idx = dr.arange(mi.UInt32, w * h)
        row = idx // w
        col = idx - w * row
        sample = mi.Vector2f(mi.Float(col), mi.Float(row)) + sampler.next_2d()
        scale = mi.ScalarVector2f(np.float32(1) / np.float32(w), np.float32(1) / np.float32(h))
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(dr.fma(sample, scale, mi.ScalarVector2f(0, 0))),
                                   mi.Point2f(0.5))
        rays = (mi.Vector3f(ray.o), mi.Vector3f(ray.d), mi.Float(ray.maxt))
        dr.eval(rays)
        cache[rotation] = rays
        return rays

    def _rays(self, pos: np.ndarray):
        """The primary rays of the views at ``pos`` in one wavefront (see :meth:`render_many`)."""
        import drjit as dr

        c, mi = self.cfg, self.mi
        k = c.supersample
        n_pix = c.width * k * c.height * k
        groups: dict[bytes, int] = {}
        group, translation = [], []
        for p in pos:
            m = np.array(mi.ScalarTransform4f().look_at(origin=p.tolist(), target=[p[0], p[1], 0.0],
                                                         up=[0, 1, 0]).matrix, dtype=np.float32)
            translation.append(m[:3, 3].copy())
            m[:3, 3] = 0
            group.append(groups.setdefault(m.tobytes(), len(groups)))
        per_group = [self._view_rays(r) for r in groups]
        o_g = mi.Vector3f(*(dr.concat([g[0][i] for g in per_group]) for i in range(3))) if len(per_group) > 1 \
            else per_group[0][0]
        d_g = mi.Vector3f(*(dr.concat([g[1][i] for g in per_group]) for i in range(3))) if len(per_group) > 1 \
            else per_group[0][1]
        maxt_g = dr.concat([g[2] for g in per_group]) if len(per_group) > 1 else per_group[0][2]
        n = len(pos)
        idx = dr.arange(mi.UInt32, n * n_pix)
        view = idx // n_pix
        pix = idx - view * n_pix
        src = dr.gather(mi.UInt32, mi.UInt32(np.array(group, dtype=np.uint32)), view) * n_pix + pix
        t = np.array(translation, dtype=np.float32)
        origin = dr.gather(mi.Vector3f, mi.Vector3f(t[:, 0], t[:, 1], t[:, 2]), view) + \
            dr.gather(mi.Vector3f, o_g, src)
        ray = mi.Ray3f(origin, dr.gather(mi.Vector3f, d_g, src))
        ray.maxt = dr.gather(mi.Float, maxt_g, src)
        dr.eval(ray)  # rays first: fused into the intersection kernel they cost ~10x more
        return ray

    def _trace_chunk(self, pos: np.ndarray) -> tuple[np.ndarray, Any, int]:
        """The normal (numpy, N·H·k·W·k × 3) and shape-id (Dr.Jit UInt32) AOVs of the
        views at ``pos``, and their number."""
        import drjit as dr

        mi, n = self.mi, len(pos)
        ray = self._rays(pos)
        si = self.scene.ray_intersect(ray, mi.RayFlags.All, True)
        valid = si.is_valid()
        shape_id = dr.select(valid, dr.reinterpret_array(mi.UInt32, si.shape), 0)
        normal = dr.select(valid, si.sh_frame.n, mi.Vector3f(0))
        dr.eval(shape_id, normal)
        # Component by component: np.array of a whole Vector3f takes a slow path (~0.2 s per 1e6 rays).
        normal_np = np.stack([np.array(normal.x), np.array(normal.y), np.array(normal.z)], axis=-1)
        return normal_np, shape_id, n

    def _shaded_chunk(self, pos: np.ndarray, lit: bool = True) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """The ``shaded`` images (N, H, W, 3; None without ``lit``: the depth alone, no
        shadow rays), person labels (N, H, W) and depth (N, H, W) of the views at ``pos``:
        the primary rays of :meth:`render_many`, then the light of the training frames
        (:mod:`~caviar_plugins.vision.shading`: one shadow ray per sample, geometric normals
        turned toward the camera, the albedo noise)."""
        import drjit as dr

        c, mi, k = self.cfg, self.mi, self.cfg.supersample
        n, h, w = len(pos), c.height, c.width
        si = self.scene.ray_intersect(self._rays(pos), mi.RayFlags.All, True)
        valid = si.is_valid()
        shape_id = dr.select(valid, dr.reinterpret_array(mi.UInt32, si.shape), 0)
        dr.eval(shape_id, si.p, si.n, si.t)
        hit = np.array(valid, dtype=bool)
        shape = np.clip(np.array(shape_id, dtype=np.int64), 0, len(self.palette) - 1)
        t = np.where(hit, np.array(si.t, dtype=float), np.nan).reshape(n, h, k, w, k)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (a pixel that sees only sky: NaN)
            depth = np.nanmean(t.transpose(0, 1, 3, 2, 4).reshape(n, h, w, k * k), axis=-1) \
                if hit.any() else np.full((n, h, w), np.nan)
        labels = self.person_of_id[shape.reshape(n, h * k, w * k)[:, ::k, ::k]]
        if not lit:
            return None, labels, depth.astype(np.float32)
        points = np.stack([np.array(si.p.x), np.array(si.p.y), np.array(si.p.z)], axis=-1).astype(float)
        normals = np.stack([np.array(si.n.x), np.array(si.n.y), np.array(si.n.z)], axis=-1).astype(float)
        eye = np.repeat(pos, h * k * w * k, axis=0)
        normals = facing(normals, points, eye)
        light = c.light()
        shadow = in_shadow(mi, self.scene, points, normals, light["sun"], hit)
        albedo = self.palette[shape].astype(float)
        vary_albedo(albedo, points, self.noisy[shape] & hit, self.seed)
        linear = shade(albedo, normals, shadow, hit, light).reshape(n, h, k, w, k, 3).mean(axis=(2, 4))
        return to_srgb8(linear), labels, depth.astype(np.float32)

    def _shade_batch(self, normal: np.ndarray, shape_id, n: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_shade` of ``n`` views, bit for bit: the Lambert term in numpy (its
        dot product's rounding is numpy's), the palette, product and k × k sum in one
        Dr.Jit kernel in float64 with the same operations in the same order, the
        division and sRGB in numpy."""
        import drjit as dr

        c, mi, k = self.cfg, self.mi, self.cfg.supersample
        sun = np.array([-0.3, -0.2, 1.0]) / np.linalg.norm([-0.3, -0.2, 1.0])
        f64 = mi.Float64  # (the active variant's: CUDA or LLVM)
        lambert = f64(0.45 + 0.55 * np.clip(normal @ sun, 0, 1))
        shape = dr.minimum(shape_id, len(self.palette) - 1)
        w, h = c.width, c.height
        o = dr.arange(mi.UInt32, n * h * w)
        view = o // (h * w)
        rest = o - view * (h * w)
        row = rest // w
        col = rest - row * w
        base = view * (h * w * k * k) + row * (k * w * k) + col * k
        total: list = [None, None, None]
        for i in range(k):
            for j in range(k):
                s = base + i * (w * k) + j
                sid = dr.gather(mi.UInt32, shape, s)
                lam = dr.gather(f64, lambert, s)
                for ch in range(3):
                    v = f64(dr.gather(mi.Float, self._palette_dr[ch], sid)) * lam
                    total[ch] = v if total[ch] is None else total[ch] + v
        labels_id = dr.gather(mi.UInt32, shape, base)
        dr.eval(total, labels_id)
        linear = np.stack([np.array(t) for t in total], axis=-1).reshape(n, h, w, 3) / (k * k)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
        labels = self.person_of_id[np.array(labels_id).reshape(n, h, w)]
        return (255 * np.clip(srgb, 0, 1) + 0.5).astype(np.uint8), labels

    def _shade(self, normal: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour, Lambert shading, supersample average and sRGB of the AOVs of one view
        (H·k, W·k) or of a stack of views (N, H·k, W·k): the same arithmetic per pixel."""
        c, k = self.cfg, self.cfg.supersample
        lead = shape.shape[:-2]
        shape = np.clip(shape, 0, len(self.palette) - 1)
        sun = np.array([-0.3, -0.2, 1.0]) / np.linalg.norm([-0.3, -0.2, 1.0])
        linear = self.palette[shape] * (0.45 + 0.55 * np.clip(normal @ sun, 0, 1))[..., None]
        linear = linear.reshape(*lead, c.height, k, c.width, k, 3)
        # The mean over each pixel's k × k samples, summed in the order numpy's
        # mean(axis=(-4, -2)) sums them (row by row): the same bits, 3x faster.
        total = linear[..., 0, :, 0, :]
        for i in range(k):
            for j in range(k):
                if i or j:
                    total = total + linear[..., i, :, j, :]
        linear = total / (k * k)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
        labels = self.person_of_id[shape[..., ::k, ::k]]
        return (255 * np.clip(srgb, 0, 1) + 0.5).astype(np.uint8), labels

    def render_labelled(self, position) -> tuple[np.ndarray, np.ndarray]:
        """The image and the per-pixel target index (-1: no person), from the shape
        seen at each pixel's first sample."""
        c, mi = self.cfg, self.mi
        k = c.supersample
        pos = [float(v) for v in position]
        sensor = mi.load_dict({
            "type": "perspective", "fov": c.fov_deg, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=pos, target=[pos[0], pos[1], 0.0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": c.width * k, "height": c.height * k, "rfilter": {"type": "box"},
                     "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"},
            "sampler": {"type": "independent", "sample_count": 1},
        })
        aov = np.array(mi.render(self.scene, sensor=sensor, spp=1))
        return self._shade(aov[..., -4:-1], np.rint(aov[..., -1]).astype(np.int64))


FILE = "file"
"""Last token of the PNG artifact's topic, ``3D.camera.<UE_Id>.file``."""
DEPTH = "depth"
"""Last token of the depth image's topic, ``3D.camera.<UE_Id>.depth``."""


class Camera(caviar.Plugin):
    """Renders each UAV's nadir camera image and publishes it as a binary payload on
    ``3D.camera.<UE_Id>`` (uint8, H × W × 3); with ``save`` also as PNG artifacts on
    ``3D.camera.<UE_Id>.file``; with ``depth`` the depth image beside it on
    ``3D.camera.<UE_Id>.depth`` (float32, H × W, metres from the camera, NaN where only sky).
    ``render = "shaded"`` renders as the detector's training frames are lit (sun, cast
    shadows, sky, exposure); ``flat`` (the default) as the loop always has."""

    subscribe = [POSITIONS]
    publishes = (every_ue(CAMERA), f"{every_ue(CAMERA)}.{FILE}", f"{every_ue(CAMERA)}.{DEPTH}")
    stateless = True  # each step's images from that step's positions (the last ones kept are a shortcut)

    @dataclasses.dataclass
    class Params(VisualConfig):
        save: bool = False
        batch: bool = True
        """Render all UAVs of a step in one wavefront of rays (:meth:`VisualScene.render_many`,
        the same images); ``false``: one Mitsuba render per UAV, as before issue #18."""
        still_frames: bool = True
        """A UAV where it was at its last image gets that image again without a render
        (the scene is static and the renderer seeded: it is the same image, bit for bit;
        a hovering UAV costs nothing); ``false``: every image rendered."""
        depth: bool = False
        """Also publish each image's depth image (``3D.camera.<UE_Id>.depth``)."""
        ue_types: list[str] = dataclasses.field(default_factory=list)
        """The UE types that carry a camera (``["UAV"]``: not the cars and pedestrians of a
        city); empty: every UE that publishes a position."""

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        cfg = VisualConfig(**{f.name: getattr(p, f.name) for f in dataclasses.fields(VisualConfig)})
        self.visual = VisualScene(cfg, seed=ctx.seed, base_dir=ctx.config_dir)
        # UE -> (position, image, depth or None) of its last image
        self.last: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}

    def _render(self, positions: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """(image, depth or None) of each view."""
        p = self.ctx.params
        if not positions:
            return []
        if p.depth:
            return [(im, d) for im, d in self.visual.render_depth(positions)]
        if p.batch or p.render == "shaded":  # (the shaded renderer is the batched one)
            return [(im, None) for im, _ in self.visual.render_many(positions)]
        return [(self.visual.render(pos), None) for pos in positions]

    def step(self, t, inbox):
        latest = {}
        p = self.ctx.params
        for m in inbox.on(POSITIONS):
            if not p.ue_types or m.data.get("UE_type") in p.ue_types:
                latest[m.data["UE_Id"]] = read_position(m.data)
        frames = {ue: self.last[ue][1:] for ue, pos in latest.items()
                  if p.still_frames and ue in self.last and np.array_equal(self.last[ue][0], pos)}
        todo = [ue for ue in latest if ue not in frames]
        for ue, frame in zip(todo, self._render([latest[ue] for ue in todo]), strict=True):
            frames[ue] = frame
            if p.still_frames:
                self.last[ue] = (latest[ue], *frame)
        for ue in latest:
            image, depth = frames[ue]
            yield per_ue(CAMERA, ue), image
            if depth is not None:
                yield f"{per_ue(CAMERA, ue)}.{DEPTH}", depth
            if self.ctx.params.save:
                path = self.ctx.artifact_dir / f"{ue}-{self.ctx.step:06d}.png"
                write_png(path, image)
                yield f"{per_ue(CAMERA, ue)}.{FILE}", caviar.Artifact(path)


def write_png(path, image: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, image)
