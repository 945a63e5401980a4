"""UAV camera images rendered with Mitsuba 3 from the same 3D scene as the radio.

A frame is cheap because it is not path traced: one pass of Mitsuba's AOV
integrator gives each pixel's surface colour (albedo), normal and shape index;
a sun-and-sky Lambert term is applied in numpy. 160 × 120 at 2 samples per pixel
takes under 10 ms on 2 CPU cores (the default path tracer: about 2.6 s at 320 × 240,
16 spp). The shape index gives exact person masks: the labels for training and
evaluating the detector.

The visual scene uses Mitsuba's RGB variant; the radio scene (Sionna RT) uses its
own. :func:`variant` switches and restores, so both live in one process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np

import caviar
from caviar_plugins import DATA
from caviar_plugins.frames import read_waypoints
from caviar_plugins.mobility import Path
from caviar_plugins.radio import SCENES, configure_drjit

VARIANT = "llvm_ad_rgb"
CLOTHES = [(0.95, 0.35, 0.05), (0.85, 0.08, 0.08), (0.95, 0.85, 0.1), (0.1, 0.25, 0.85), (0.55, 0.1, 0.6)]
SKIN = (0.8, 0.6, 0.45)


@contextlib.contextmanager
def variant(name: str = VARIANT):
    """Runs the block in Mitsuba variant ``name`` and restores the radio's variant.
    Sionna RT picks its variant when imported, and only if none is set yet: import
    it first so that the render variant never becomes the radio's."""
    configure_drjit()
    import mitsuba as mi
    import sionna.rt  # noqa: F401

    with mi.util.scoped_set_variant(name):
        yield mi


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
    spp: int = 2


class VisualScene:
    """Buildings, ground, persons and distractors; renders nadir views."""

    def __init__(self, cfg: VisualConfig, seed: int = 0):
        self.cfg = cfg
        rng = np.random.default_rng(seed)
        meshes = SCENES / cfg.scene / "meshes"
        with variant() as mi:
            d = {
                "type": "scene",
                "integrator": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,id:shape_index"},
                "buildings": {"type": "ply", "filename": str(meshes / "map_2_osm_buildings.ply"),
                              "bsdf": _diffuse((0.55, 0.55, 0.6))},
                "ground": {"type": "ply", "filename": str(meshes / "Plane.ply"), "bsdf": _diffuse((0.22, 0.45, 0.16))},
            }
            for i, (x, y) in enumerate(cfg.targets):
                yaw = float(rng.uniform(0, 180))
                d[f"person{i}-body"] = {
                    "type": "cube", "bsdf": _diffuse(CLOTHES[i % len(CLOTHES)]),
                    "to_world": mi.ScalarTransform4f().translate([x, y, 0.15]).rotate([0, 0, 1], yaw).scale([0.8, 0.25, 0.15])}
                hx, hy = x + 0.95 * math.cos(math.radians(yaw)), y + 0.95 * math.sin(math.radians(yaw))
                d[f"person{i}-head"] = {"type": "sphere", "center": [hx, hy, 0.15], "radius": 0.14,
                                        "bsdf": _diffuse(SKIN)}
            path = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
            for j in range(cfg.distractors):
                p = path.at(rng.uniform(0, path.length)) + np.r_[rng.normal(0, 4, 2), 0]
                if rng.uniform() < 0.5:
                    r = float(rng.uniform(0.4, 1.2))
                    d[f"bush{j}"] = {"type": "sphere", "center": [p[0], p[1], r * 0.6], "radius": r,
                                     "bsdf": _diffuse((0.08, 0.28, 0.06))}
                else:
                    s = float(rng.uniform(0.2, 0.5))
                    d[f"rock{j}"] = {"type": "cube", "bsdf": _diffuse((0.45, 0.42, 0.38)),
                                     "to_world": mi.ScalarTransform4f().translate([p[0], p[1], s]).scale([s * 1.3, s, s])}
            self.scene = mi.load_dict(d)
            # The shape_index AOV holds each shape's registry id (its pointer as an integer).
            import drjit as dr

            names = [s.id() for s in self.scene.shapes()]
            ids = np.array(dr.reinterpret_array(mi.UInt32, self.scene.shapes_dr()))
            self.person_of_shape = {int(i): int(n[len("person"):].split("-")[0])
                                    for i, n in zip(ids, names) if n.startswith("person")}

    def render(self, position) -> np.ndarray:
        """An sRGB uint8 image (H, W, 3) seen from ``position`` straight down."""
        return self.render_labelled(position, labels=False)[0]

    def render_labelled(self, position, labels: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The image and the per-pixel target index (-1: no person). Labels come from a
        1-sample pass: averaged shape ids at edges would be meaningless."""
        image, shape = self._render(position, self.cfg.spp)
        if not labels:
            return image, None
        if self.cfg.spp != 1:
            shape = self._render(position, 1)[1]
        out = np.full(shape.shape, -1)
        for sid, person in self.person_of_shape.items():
            out[shape == sid] = person
        return image, out

    def _render(self, position, spp: int):
        c = self.cfg
        with variant() as mi:
            pos = [float(v) for v in position]
            target = [pos[0], pos[1], 0.0]
            sensor = mi.load_dict({
                "type": "perspective", "fov": c.fov_deg, "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(origin=pos, target=target, up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": c.width, "height": c.height, "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": spp},
            })
            img = np.array(mi.render(self.scene, sensor=sensor, spp=spp))
        albedo, normal, shape = img[..., :3], img[..., 3:6], np.rint(img[..., 6]).astype(int)
        sun = np.array([-0.3, -0.2, 1.0]) / np.linalg.norm([-0.3, -0.2, 1.0])
        linear = np.clip(albedo * (0.45 + 0.55 * np.clip(normal @ sun, 0, 1))[..., None], 0, 1)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        return (255 * srgb + 0.5).astype(np.uint8), shape


def _diffuse(rgb):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


CAMERA = "3D.camera"


class Camera(caviar.Plugin):
    """Renders each UAV's nadir camera image and publishes it as a binary payload on
    ``3D.camera.<UE_Id>`` (uint8, H × W × 3); with ``save`` also as PNG artifacts."""

    subscribe = ["3D.mobility.positions"]

    @dataclasses.dataclass
    class Params(VisualConfig):
        save: bool = False

    def setup(self, ctx):
        self.ctx = ctx
        p = ctx.params
        cfg = VisualConfig(**{f.name: getattr(p, f.name) for f in dataclasses.fields(VisualConfig)})
        self.visual = VisualScene(cfg, seed=ctx.seed)

    def step(self, t, inbox):
        latest = {}
        for m in inbox.on("3D.mobility.positions"):
            latest[m.data["UE_Id"]] = m.data["position"]
        for ue, pos in latest.items():
            image = self.visual.render([pos["x"], pos["y"], pos["z"]])
            yield f"{CAMERA}.{ue}", image
            if self.ctx.params.save:
                path = self.ctx.artifact_dir / f"{ue}-{self.ctx.step:06d}.png"
                write_png(path, image)
                yield f"{CAMERA}.{ue}.file", caviar.Artifact(path)


def write_png(path, image: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, image)
