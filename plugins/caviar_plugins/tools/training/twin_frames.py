"""Training, validation and test frames for a YOLO person detector, labelled by the twin.

The renderer knows which pixel belongs to which person, so the labels are exact: a
person's YOLO box is the bounding box of the pixels whose first visible shape is one of
its parts. The frames are not the SAR route's and not the camera plugin's flat colours:

* **flights**: straight passes in random directions over the Central Park scene (not the
  SAR route), altitude 6-20 m, the camera's image-up along the heading;
* **persons**: placed at random near each flight, on whatever surface is under them
  (ground or roof), in four poses (lying, lying with arms spread, sitting, standing), body
  size x0.85-1.15, clothes of any hue and brightness (dull greys and greens included), five
  skin tones;
* **distractors**: bushes, rocks, and person-sized benches and bins in bright colours;
* **light**: a sun at 15-75 deg elevation and any azimuth, warmer when low, with cast
  shadows (one shadow ray per sample, flat-faceted geometric normals), a sky term of
  0.25-0.5, exposure x0.75-1.25, and ground, road and roof albedo varied by a 0.5 m value
  noise.

Each frame is one Mitsuba AOV pass (position, normal, shape) at 2 x 2 samples per pixel and
one shadow-ray pass; the cost per frame is measured by :func:`write_dataset` and kept in
``meta.json``.

    python -m caviar_plugins.tools.training.twin_frames OUT [--train 1200 --val 240 --test 240]

``OUT/data.yaml`` is an Ultralytics dataset; ``OUT/images/<split>/*.png`` and
``OUT/labels/<split>/*.txt`` (``0 cx cy w h``, normalised), ``OUT/meta.json`` the seeds,
counts and measured cost. Training frames carry the image link's packet loss (as the
detector meets them in the loop); validation and test frames are clean, and the test
frames are degraded at each loss level when evaluated (:mod:`caviar_plugins.tools.training.yolo_eval`).
"""

from __future__ import annotations

import argparse
import colorsys
import dataclasses
import json
import math
import pathlib
import time
from typing import Any

import numpy as np

from caviar_plugins.assets import DATA
from caviar_plugins.mobility.waypoints import read_waypoints
from caviar_plugins.rt.drjit_setup import mitsuba
from caviar_plugins.vision.camera import _scene_meshes, shape_ids
from caviar_plugins.vision.image_link import packet_loss
from caviar_plugins.vision.shading import daylight, facing, in_shadow, shade, to_srgb8, vary_albedo

SPLIT_SEEDS = {"train": 101, "val": 202, "test": 303}
"""Each split has its own scene (persons, distractors) and flights, from its own seed."""
TRAIN_LOSS_RATES = (0.0, 0.0, 0.01, 0.25, 0.5)
"""Packet-loss rates drawn for training frames (the image link's table, loss-free twice)."""
SKIN_TONES = [(0.94, 0.76, 0.62), (0.84, 0.62, 0.47), (0.66, 0.46, 0.32), (0.45, 0.3, 0.2), (0.3, 0.2, 0.14)]
MIN_BOX_PIXELS = 6
"""A person whose visible pixels are fewer than this (image resolution) gets no box."""


@dataclasses.dataclass
class FrameConfig:
    width: int = 160
    height: int = 120
    fov_deg: float = 70.0
    supersample: int = 2
    altitude_m: tuple[float, float] = (6.0, 20.0)
    frames_per_flight: int = 8
    spacing_m: float = 6.0
    """Along-track distance between a flight's frames."""
    persons_per_100m: float = 20.0
    """Persons placed near each flight, per 100 m of it (3.5 m standard deviation across its track)."""
    distractors_per_100m: float = 12.0
    empty_share: float = 0.15
    """Share of flights with no person at all (frames with nothing to find)."""


@dataclasses.dataclass
class Person:
    index: int
    pose: str
    x: float
    y: float
    z: float


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def _box(mi, centre, size, yaw_deg: float, tilt: tuple[float, float, float] | None = None) -> dict:
    """A cube of full ``size`` (x, y, z) centred at ``centre``, turned by ``yaw_deg``."""
    t = mi.ScalarTransform4f().translate([float(c) for c in centre]).rotate([0, 0, 1], yaw_deg)
    if tilt is not None:
        t = t.rotate([1, 0, 0], tilt[0]).rotate([0, 1, 0], tilt[1])
    return {"type": "cube", "to_world": t.scale([s / 2 for s in size])}


def _person_parts(mi, rng: np.random.Generator, pose: str, x: float, y: float, z: float) -> list[tuple[str, dict]]:
    """Mitsuba shapes of one person in ``pose``, standing on the surface at height z."""
    s = float(rng.uniform(0.85, 1.15))
    yaw = float(rng.uniform(0, 360))
    c, si = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))

    def along(d: float, side: float = 0.0) -> tuple[float, float]:
        return x + d * c - side * si, y + d * si + side * c

    parts: list[tuple[str, dict]] = []
    if pose in ("lying", "spread"):
        parts.append(("body", _box(mi, (x, y, z + 0.13 * s), (1.45 * s, 0.45 * s, 0.26 * s), yaw)))
        hx, hy = along(0.88 * s)
        parts.append(("head", {"type": "sphere", "center": [hx, hy, z + 0.12 * s], "radius": 0.12 * s}))
        if pose == "spread":
            for side in (-1, 1):
                ax, ay = along(0.45 * s, side * 0.5 * s)
                parts.append(("arm", _box(mi, (ax, ay, z + 0.07 * s), (0.14 * s, 0.6 * s, 0.12 * s), yaw + side * 20)))
    elif pose == "sitting":
        parts.append(("body", _box(mi, (x, y, z + 0.35 * s), (0.3 * s, 0.45 * s, 0.7 * s), yaw)))
        lx, ly = along(0.35 * s)
        parts.append(("legs", _box(mi, (lx, ly, z + 0.08 * s), (0.55 * s, 0.4 * s, 0.16 * s), yaw)))
        parts.append(("head", {"type": "sphere", "center": [x, y, z + 0.84 * s], "radius": 0.12 * s}))
    else:  # standing
        parts.append(("body", _box(mi, (x, y, z + 0.78 * s), (0.28 * s, 0.48 * s, 1.56 * s), yaw)))
        parts.append(("head", {"type": "sphere", "center": [x, y, z + 1.68 * s], "radius": 0.12 * s}))
    return parts


def _clothes(rng: np.random.Generator) -> tuple[float, float, float]:
    """Any hue; a third of them dull (low saturation or dark)."""
    h = float(rng.uniform())
    if rng.uniform() < 0.33:
        sat, val = float(rng.uniform(0.0, 0.35)), float(rng.uniform(0.15, 0.6))
    else:
        sat, val = float(rng.uniform(0.5, 1.0)), float(rng.uniform(0.45, 1.0))
    r, g, b = colorsys.hsv_to_rgb(h, sat, val)
    return (r, g, b)


class TwinFrames:
    """The scene of one split (persons and distractors along its flights) and its frames."""

    POSES = ("lying", "spread", "sitting", "standing")

    def __init__(self, cfg: FrameConfig, seed: int, flights: int):
        self.cfg = cfg
        self.rng = rng = np.random.default_rng(seed)
        mi = self.mi = mitsuba()
        base: dict = {"type": "scene"}
        colours = _scene_meshes("central_park", None, base)
        self._static = mi.load_dict(base)
        route = np.asarray(read_waypoints(DATA / "central_park_path0_scene.csv"), dtype=float)
        lo, hi = route[:, :2].min(axis=0) - 40.0, route[:, :2].max(axis=0) + 40.0
        self.flights: list[dict] = []
        d = dict(base)
        d["integrator"] = {"type": "aov", "aovs": "pp:position,ng:geo_normal,id:shape_index"}
        self.persons: list[Person] = []
        person_parts: dict[str, int] = {}
        kinds: dict[str, str] = {}  # shape id -> "ground" / "road" / "roof" / other (albedo noise)
        for sid in colours:
            low = sid.lower()
            kinds[sid] = "ground" if ("ground" in low or "plane" in low) else "road" if "road" in low else "roof"
        length = cfg.frames_per_flight * cfg.spacing_m
        for f in range(flights):
            start = rng.uniform(lo, hi)
            heading = float(rng.uniform(0, 360))
            u = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
            altitude = _uniform(rng, cfg.altitude_m)
            self.flights.append({"start": start, "dir": u, "heading": heading, "altitude": altitude})
            empty = rng.uniform() < cfg.empty_share
            n_persons = 0 if empty else rng.poisson(cfg.persons_per_100m * length / 100)
            side = np.array([-u[1], u[0]])
            spots = [start + u * rng.uniform(-3, length + 3) + side * rng.normal(0, 3.5) for _ in range(n_persons)]
            for xy, z in zip(spots, self._surfaces(np.array(spots)), strict=True):
                if np.isnan(z):
                    continue
                z = float(z)
                pose = self.POSES[int(rng.integers(len(self.POSES)))]
                k = len(self.persons)
                self.persons.append(Person(k, pose, float(xy[0]), float(xy[1]), z))
                cloth, skin = _clothes(rng), SKIN_TONES[int(rng.integers(len(SKIN_TONES)))]
                for j, (part, shape) in enumerate(_person_parts(mi, rng, pose, float(xy[0]), float(xy[1]), z)):
                    sid = f"person{k}-{part}{j}"
                    d[sid] = shape
                    colours[sid] = skin if part == "head" else cloth
                    person_parts[sid] = k
                    kinds[sid] = "person"
            n_things = rng.poisson(cfg.distractors_per_100m * length / 100)
            spots = [start + u * rng.uniform(-5, length + 5) + side * rng.normal(0, 6) for _ in range(n_things)]
            for j, (xy, z) in enumerate(zip(spots, self._surfaces(np.array(spots)), strict=True)):
                if np.isnan(z):
                    continue
                z = float(z)
                sid = f"flight{f}-thing{j}"
                kind = rng.uniform()
                if kind < 0.4:
                    r = float(rng.uniform(0.4, 1.3))
                    d[sid] = {"type": "sphere", "center": [float(xy[0]), float(xy[1]), z + 0.6 * r], "radius": r}
                    colours[sid] = colorsys.hsv_to_rgb(float(rng.uniform(0.2, 0.4)), 0.7, float(rng.uniform(0.2, 0.4)))
                elif kind < 0.7:
                    size = float(rng.uniform(0.2, 0.6))
                    d[sid] = _box(mi, (xy[0], xy[1], z + size / 2), (size * 1.4, size, size),
                                  float(rng.uniform(0, 360)))
                    grey = float(rng.uniform(0.3, 0.55))
                    colours[sid] = (grey, grey * 0.95, grey * 0.9)
                else:  # benches, bins: person-sized, bright
                    dims = (float(rng.uniform(0.4, 1.8)), float(rng.uniform(0.35, 0.6)), float(rng.uniform(0.4, 0.9)))
                    d[sid] = _box(mi, (xy[0], xy[1], z + dims[2] / 2), dims, float(rng.uniform(0, 360)))
                    colours[sid] = _clothes(rng)
                kinds[sid] = "thing"
        self.scene = mi.load_dict(d)
        ids, names = shape_ids(self.scene)
        size = int(ids.max()) + 1
        self.palette = np.zeros((size, 3), dtype=np.float64)
        self.person_of_id = np.full(size, -1)
        self.noisy = np.zeros(size, dtype=bool)
        for i, name in zip(ids, names, strict=True):
            self.palette[i] = colours[name]
            self.person_of_id[i] = person_parts.get(name, -1)
            self.noisy[i] = kinds.get(name) in ("ground", "road", "roof")
        self.seed = seed

    def _surfaces(self, xy: np.ndarray) -> np.ndarray:
        """Height of the first surface under each (x, y) (n, 2), from above; NaN where there is
        none (off the scene). One wavefront: the points are data, not kernel constants."""
        mi = self.mi
        xy = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
        if len(xy) == 0:
            return np.zeros(0)
        n = len(xy)
        ray = mi.Ray3f(mi.Point3f(mi.Float(np.ascontiguousarray(xy[:, 0])), mi.Float(np.ascontiguousarray(xy[:, 1])),
                                  mi.Float(np.full(n, 500.0, dtype=np.float32))),
                       mi.Vector3f(mi.Float(np.zeros(n, np.float32)), mi.Float(np.zeros(n, np.float32)),
                                   mi.Float(np.full(n, -1.0, dtype=np.float32))))
        si = self._static.ray_intersect(ray)
        valid = np.asarray(si.is_valid(), dtype=bool)
        return np.where(valid, np.asarray(si.p.z, dtype=float), np.nan)

    def views(self):
        """(flight index, camera position, heading) of every frame, flight by flight."""
        steps = np.arange(self.cfg.frames_per_flight) * self.cfg.spacing_m
        xy = np.concatenate([fl["start"] + fl["dir"] * steps[:, None] for fl in self.flights])
        ground = np.nan_to_num(self._surfaces(xy), nan=0.0)
        for i, (point, z) in enumerate(zip(xy, ground, strict=True)):
            fl = self.flights[i // len(steps)]
            yield i // len(steps), np.array([point[0], point[1], z + fl["altitude"]]), fl["heading"]

    def light(self, rng: np.random.Generator) -> dict[str, Any]:
        """A random time of day: sun direction and colour, sky term, exposure."""
        elevation = float(rng.uniform(15, 75))
        azimuth = float(rng.uniform(0, 360))
        return daylight(elevation, azimuth, sky=float(rng.uniform(0.25, 0.5)), exposure=float(rng.uniform(0.75, 1.25)))

    def render(self, position, heading_deg: float, light: dict) -> tuple[np.ndarray, np.ndarray]:
        """An sRGB uint8 image (H, W, 3) seen straight down from ``position``, image-up along
        ``heading_deg``, and the per-sample person index (H·k, W·k), -1 where none."""
        import drjit as dr

        c, mi, k = self.cfg, self.mi, self.cfg.supersample
        pos = [float(v) for v in position]
        h = math.radians(heading_deg)
        sensor = mi.load_dict({
            "type": "perspective", "fov": c.fov_deg, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=pos, target=[pos[0], pos[1], pos[2] - 10.0],
                                                        up=[math.cos(h), math.sin(h), 0.0]),
            "film": {"type": "hdrfilm", "width": c.width * k, "height": c.height * k, "rfilter": {"type": "box"},
                     "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"},
            "sampler": {"type": "independent", "sample_count": 1},
        })
        aov = np.array(mi.render(self.scene, sensor=sensor, spp=1))
        p, n = aov[..., -7:-4].reshape(-1, 3), aov[..., -4:-1].reshape(-1, 3)
        shape = np.clip(np.rint(aov[..., -1]).astype(np.int64), 0, len(self.palette) - 1).reshape(-1)
        hit = shape > 0
        # Normals towards the camera (Mitsuba's cube and sphere normals point out already;
        # flipped where a face is seen from behind).
        n = facing(n, p, np.array(pos))
        shadow = in_shadow(mi, self.scene, p, n, light["sun"], hit)
        dr.eval()
        albedo = self.palette[shape]
        vary_albedo(albedo, p, self.noisy[shape], self.seed)
        linear = shade(albedo, n, shadow, hit, light)
        linear = linear.reshape(c.height, k, c.width, k, 3).mean(axis=(1, 3))
        labels = self.person_of_id[shape].reshape(c.height * k, c.width * k)
        return to_srgb8(linear), labels


def yolo_boxes(labels: np.ndarray, supersample: int, min_pixels: int = MIN_BOX_PIXELS) -> list[tuple[int, float, float,
                                                                                                      float, float]]:
    """Each visible person's box from per-sample labels (H·k, W·k): (person, x0, y0, x1, y1) in
    image pixels, the bounding box of its samples; persons with fewer than ``min_pixels``
    pixels' worth of samples are left out."""
    k = supersample
    out = []
    for person in np.unique(labels[labels >= 0]):
        rows, cols = np.nonzero(labels == person)
        if len(rows) < min_pixels * k * k:
            continue
        out.append((int(person), cols.min() / k, rows.min() / k, (cols.max() + 1) / k, (rows.max() + 1) / k))
    return out


def yolo_lines(boxes, width: int, height: int) -> str:
    """Ultralytics label lines: ``0 cx cy w h``, normalised to the image."""
    return "".join(f"0 {(x0 + x1) / 2 / width:.6f} {(y0 + y1) / 2 / height:.6f} {(x1 - x0) / width:.6f} "
                   f"{(y1 - y0) / height:.6f}\n" for _, x0, y0, x1, y1 in boxes)


def write_png(path: pathlib.Path, image: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(image).save(path)


def read_labels(path: pathlib.Path, width: int, height: int) -> np.ndarray:
    """Boxes (x0, y0, x1, y1) in pixels from an Ultralytics label file."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    out = np.array([[float(v) for v in r[1:5]] for r in rows], dtype=float).reshape(-1, 4)
    cx, cy, w, h = out[:, 0] * width, out[:, 1] * height, out[:, 2] * width, out[:, 3] * height
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)


def write_dataset(out: pathlib.Path, counts: dict[str, int], cfg: FrameConfig | None = None,
                  progress: bool = True) -> dict:
    """Renders the splits into ``out`` (an Ultralytics dataset); returns what ``meta.json`` holds."""
    from tqdm import tqdm

    cfg = cfg or FrameConfig()
    out = pathlib.Path(out)
    meta: dict[str, Any] = {"config": dataclasses.asdict(cfg), "splits": {}}
    seconds, frames_total = 0.0, 0
    for split, count in counts.items():
        if count <= 0:
            continue
        seed = SPLIT_SEEDS[split]
        flights = -(-count // cfg.frames_per_flight)
        t0 = time.perf_counter()
        twin = TwinFrames(cfg, seed, flights)
        build_s = time.perf_counter() - t0
        (out / "images" / split).mkdir(parents=True, exist_ok=True)
        (out / "labels" / split).mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng(seed + 1)
        boxes_total, empty, render_s, poses = 0, 0, 0.0, dict.fromkeys(TwinFrames.POSES, 0)
        lights: dict[int, dict] = {}
        rates = []
        views = list(twin.views())[:count]
        for i, (f, pos, heading) in enumerate(tqdm(views, desc=f"{split} frames", disable=not progress,
                                                   unit="frame")):
            # One light per flight (the flight's first draw; each frame draws one, which keeps the
            # random stream of the frames the committed model was trained on).
            light = lights.setdefault(f, twin.light(rng))
            t1 = time.perf_counter()
            image, labels = twin.render(pos, heading, light)
            render_s += time.perf_counter() - t1
            rate = float(rng.choice(TRAIN_LOSS_RATES)) if split == "train" else 0.0
            if rate:
                image = packet_loss(image, rate, rng)
            rates.append(rate)
            boxes = yolo_boxes(labels, cfg.supersample)
            for person, *_ in boxes:
                poses[twin.persons[person].pose] += 1
            boxes_total += len(boxes)
            empty += not boxes
            name = f"{split}-{i:05d}"
            write_png(out / "images" / split / f"{name}.png", image)
            (out / "labels" / split / f"{name}.txt").write_text(yolo_lines(boxes, cfg.width, cfg.height))
        seconds += render_s
        frames_total += len(views)
        meta["splits"][split] = {"seed": seed, "frames": len(views), "flights": flights, "boxes": boxes_total,
                                 "frames_without_person": empty, "boxes_by_pose": poses,
                                 "persons_placed": len(twin.persons), "scene_build_s": round(build_s, 2),
                                 "loss_rates": {f"{r:.2f}": rates.count(r) for r in sorted(set(rates))}}
    meta["render_s_per_frame"] = round(seconds / max(1, frames_total), 4)
    meta["note"] = ("render_s_per_frame: one AOV pass (position, normal, shape) at 2 x 2 samples per pixel, the "
                    "shadow rays and the shading, on this machine's CPU (Dr.Jit LLVM)")
    (out / "data.yaml").write_text(f"path: {out.resolve()}\ntrain: images/train\nval: images/val\n"
                                   f"test: images/test\nnames:\n  0: person\n")
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.training.twin_frames", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--train", type=int, default=1200)
    ap.add_argument("--val", type=int, default=240)
    ap.add_argument("--test", type=int, default=240)
    args = ap.parse_args(argv)
    meta = write_dataset(args.out, {"train": args.train, "val": args.val, "test": args.test})
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
