"""The camera the detector was trained for (issue #43, part 2): the shaded renderer's light
against a hand computation, shadows against a ray test, the depth image against the
camera's geometry, and the SAR loop with the shaded camera and YOLO."""

from __future__ import annotations

import math

import numpy as np
import pytest

from caviar import _core
from caviar_plugins.rt.drjit_setup import mitsuba
from caviar_plugins.vision import shading
from caviar_plugins.vision.camera import VisualConfig, VisualScene, default_targets
from configs import SAR_STAGES, episode, image_chain, module, output, route_past, run_config, the_rescue, waypoint_uav
from conftest import write_config


def test_the_light_is_the_sum_of_sky_and_sun_as_computed_by_hand():
    noon, dawn = shading.daylight(75.0, 0.0, 0.3, 1.2), shading.daylight(15.0, 90.0, 0.3, 1.2)
    np.testing.assert_allclose(noon["sun_colour"], [1.0, 0.93, 0.85])
    np.testing.assert_allclose(dawn["sun_colour"], [1.0, 0.80, 0.55])
    np.testing.assert_allclose(dawn["sun"], [0.0, math.cos(math.radians(15)), math.sin(math.radians(15))], atol=1e-12)
    albedo = np.array([[0.5, 0.4, 0.3]] * 4)
    normals = np.array([noon["sun"], noon["sun"], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    shadow = np.array([False, True, False, False])
    hit = np.array([True, True, True, False])
    linear = shading.shade(albedo.copy(), normals, shadow, hit, noon)
    np.testing.assert_allclose(linear[0], albedo[0] * (0.3 + 0.75 * noon["sun_colour"]) * 1.2)  # facing the sun
    np.testing.assert_allclose(linear[1], albedo[1] * 0.3 * 1.2)  # in shadow: the sky only
    cos = math.sin(math.radians(75.0))  # a flat surface under a sun 75° up
    np.testing.assert_allclose(linear[2], albedo[2] * (0.3 + 0.75 * cos * noon["sun_colour"]) * 1.2)
    np.testing.assert_allclose(linear[3], shading.SKY_COLOUR)


def test_a_point_under_a_roof_is_in_shadow_and_one_beside_it_is_not():
    mi = mitsuba()
    scene = mi.load_dict({"type": "scene", "ground": {"type": "rectangle",
                                                      "to_world": mi.ScalarTransform4f().scale([50, 50, 1])},
                          "roof": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0, 0, 5])
                                   .scale([2, 2, 0.1])}})
    light = shading.daylight(60.0, 0.0, 0.3, 1.0)  # the sun 60° up in the east
    points = np.array([[-2.9, 0.0, 0.0], [0.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    up = np.tile([0.0, 0.0, 1.0], (4, 1))
    shadow = shading.in_shadow(mi, scene, points, up, light["sun"], np.ones(4, bool))
    # The roof spans x in [-2, 2] at z = 5; toward the sun a ray from (x, 0, 0) crosses z = 5 at
    # x + 5 / tan 60° = x + 2.89: under the roof for x in [-4.89, -0.89].
    assert shadow.tolist() == [True, False, False, False]


def test_the_depth_image_is_the_cameras_geometry_over_flat_ground():
    cfg = VisualConfig(scene="empty", targets=[], distractors=0, render="shaded")
    vs = VisualScene(cfg, seed=1)
    h = 20.0
    ((image, depth),) = vs.render_depth([[5.0, -3.0, h]])
    assert image.shape == (120, 160, 3) and depth.shape == (120, 160) and depth.dtype == np.float32
    # Pixel (row, col) looks along tan x = u tan(fov/2), tan y = v tan(fov/2) H/W, u and v its
    # centre in [-1, 1]: the ground is h·√(1 + tan²x + tan²y) away.
    half = math.tan(math.radians(cfg.fov_deg / 2))
    u = ((np.arange(160) + 0.5) / 160 * 2 - 1) * half
    v = ((np.arange(120) + 0.5) / 120 * 2 - 1) * half * 120 / 160
    expected = h * np.sqrt(1 + u[None, :] ** 2 + v[:, None] ** 2)
    np.testing.assert_allclose(depth, expected, rtol=2e-3)
    assert depth.min() == pytest.approx(h, rel=1e-3)


def test_the_flat_renderer_is_unchanged_and_the_shaded_one_differs():
    tx, ty = default_targets()[1]
    flat = VisualScene(VisualConfig(), seed=2)
    shaded = VisualScene(VisualConfig(render="shaded"), seed=2)
    (a, la), = flat.render_many([[tx, ty, 12.0]])
    (b, lb), = shaded.render_many([[tx, ty, 12.0]])
    np.testing.assert_array_equal(a, flat.render(np.array([tx, ty, 12.0])))  # the flat one, bit for bit
    np.testing.assert_array_equal(la, lb)  # the same person pixels
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 10


def test_the_sar_loop_with_the_shaded_camera_and_yolo_rescues_the_person_in_view(tmp_path):
    tx, ty = default_targets()[1]
    route_past(tmp_path, (tx, ty))
    log = run_config(tmp_path, episode(0.5, SAR_STAGES, seed=2) + output(analysis=["3D.camera.*.depth"])
                     + waypoint_uav() + image_chain({"model": "yolo"}, camera={"render": "shaded", "depth": True}))
    assert log.status["status"] == "completed"
    depth = [np.asarray(m.data) for m in log.decoded("3D.camera.uav1.depth")]
    assert len(depth) == len(log.decoded("3D.mobility.positions")) and depth[0].shape == (120, 160)
    the_rescue(log, (tx, ty))


@pytest.mark.parametrize("params, key, says", [
    ('render = "glossy"', "render", "expected one of ['flat', 'shaded']"),
    ("sun_elevation_deg = 0.0", "sun_elevation_deg", "expected degrees in (0, 90]"),
    ("exposure = 0.0", "exposure", "exposure in (0, 4]"),
])
def test_bad_camera_input_names_the_key(tmp_path, capfd, params, key, says):
    cfg = write_config(tmp_path, episode(0.5, ["camera"], steps=1)
                       + module("camera", "camera", "camera", params, subscribe=[]))
    assert _core.main(["caviar-core", "validate", str(cfg)]) == 2
    first = capfd.readouterr().err.splitlines()[0]
    assert f"modules.camera.params.{key}:" in first and says in first, first
