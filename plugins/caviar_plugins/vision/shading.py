"""Daylight shading of the twin's frames: a sun with cast shadows, a sky term and an
exposure, over each surface's albedo. One owner of the arithmetic that both the training
frames (:mod:`caviar_plugins.tools.training.twin_frames`) and the in-loop camera's ``shaded``
renderer (:mod:`caviar_plugins.vision.camera`) use, so the detector meets in the loop the
light it was trained under::

    linear = albedo · (sky + SUN · max(n·s, 0) · [not in shadow] · sun_colour) · exposure

with ``s`` the direction toward the sun; a pixel that sees nothing is the sky's colour.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

SUN = 0.75
"""The sun's irradiance against the sky term's scale (a white surface facing it: 0.75 + sky)."""
SKY_COLOUR = np.array([0.6, 0.75, 0.95])
SHADOW_BIAS_M = 0.02
"""How far off its surface a shadow ray starts (along the normal)."""
ALBEDO_CELL_M = 0.5
"""Ground, road and roof albedo vary by ±15 % over cells of this size (value noise)."""


def daylight(elevation_deg: float, azimuth_deg: float, sky: float, exposure: float) -> dict[str, Any]:
    """The light of a time of day: the direction toward the sun, its colour (warmer when
    low: white at 75°, orange at 15°), the sky term and the exposure."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    warm = 1.0 - (elevation_deg - 15) / 60  # 1 at sunrise, 0 at noon
    sun_colour = np.array([1.0, 0.93 - 0.13 * warm, 0.85 - 0.3 * warm])
    return {"sun": np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]),
            "sun_colour": sun_colour, "sky": float(sky), "exposure": float(exposure),
            "elevation_deg": elevation_deg}


def facing(normals: np.ndarray, points: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Normals (n, 3) turned toward the viewer at ``eye`` (3 or n × 3) where a face is seen
    from behind."""
    view = points - np.asarray(eye)
    return np.where((np.sum(normals * view, axis=1) > 0)[:, None], -normals, normals)


def in_shadow(mi: Any, scene: Any, points: np.ndarray, normals: np.ndarray, sun: np.ndarray,
              hit: np.ndarray) -> np.ndarray:
    """Whether each surface point (n, 3) is hidden from the sun: one shadow ray each, from
    :data:`SHADOW_BIAS_M` off its surface along ``normals`` (false where ``hit`` is false)."""
    origin = points + normals * SHADOW_BIAS_M
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(origin[:, i], dtype=np.float32)) for i in range(3))),
                   mi.Vector3f(*(mi.Float(np.full(len(points), sun[i], dtype=np.float32)) for i in range(3))))
    return np.asarray(scene.ray_test(ray, active=mi.Bool(hit)), dtype=bool)


def vary_albedo(albedo: np.ndarray, points: np.ndarray, noisy: np.ndarray, seed: int) -> None:
    """Multiplies the albedo of the ``noisy`` points (ground, roads, roofs) by a value noise
    over :data:`ALBEDO_CELL_M` cells, ±15 % (in place)."""
    if noisy.any():
        cell = np.floor(points[noisy, :2] / ALBEDO_CELL_M).astype(np.int64)
        hsh = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ seed
        jitter = ((hsh % 1000) / 1000.0 - 0.5) * 0.3
        albedo[noisy] *= (1.0 + jitter)[:, None]


def shade(albedo: np.ndarray, normals: np.ndarray, shadow: np.ndarray, hit: np.ndarray,
          light: Mapping[str, Any]) -> np.ndarray:
    """Linear RGB (n, 3) of surface points under ``light`` (:func:`daylight`); the sky where
    ``hit`` is false."""
    lambert = np.clip(normals @ light["sun"], 0, 1) * ~shadow
    linear = albedo * (light["sky"] + SUN * lambert[:, None] * light["sun_colour"][None, :]) * light["exposure"]
    linear[~hit] = SKY_COLOUR
    return linear


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB to sRGB, 8 bits."""
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
    return (255 * np.clip(srgb, 0, 1) + 0.5).astype(np.uint8)
