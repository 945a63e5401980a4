"""What the solve does around Sionna's call (issue #53): H at the carrier is Sionna's
``cfr`` without its kernels, a receiver's H does not depend on the other receivers, and
moved UAV bodies share one geometry update with the vertices Sionna's setter would give."""

import numpy as np
import pytest

from caviar_plugins.rt import configure_drjit

configure_drjit()

from caviar_plugins.radio import RadioConfig, RadioScene  # noqa: E402
from caviar_plugins.rt import scene as rt_scene  # noqa: E402
from caviar_plugins.rt.settings import with_raytracing  # noqa: E402
from caviar_plugins.rt.solver import carrier_channels  # noqa: E402

FAST = dict(samples_per_src=20_000, max_depth=3, threads=1, shoot_cache=False)
UAVS = {"a": np.array([-60.0, 20.0, 30.0]), "b": np.array([-20.0, 40.0, 25.0]), "c": np.array([10.0, -5.0, 40.0])}


@pytest.fixture(scope="module")
def solved():
    radio = RadioScene(with_raytracing(RadioConfig, **FAST, uav_mesh=False), seed=2)
    radio.place(UAVS)
    return radio, radio.solve()


def test_the_carrier_channel_is_sionnas_cfr(solved):
    radio, links = solved
    paths = radio.last_paths
    cfr = paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")[:, :, 0, :, 0, 0]
    h, valid, tau = carrier_channels(paths, 3, radio.cfg.frequency_hz)
    assert h.dtype == np.complex64 and h.shape == (3, 4, 64)
    np.testing.assert_allclose(h, cfr, rtol=0, atol=2e-6 * np.abs(cfr).max())
    np.testing.assert_array_equal(valid, np.array(paths.valid).reshape(3, -1))
    for i, key in enumerate(radio.receivers):
        np.testing.assert_array_equal(links[key].h, h[i])
        assert links[key].n_paths == int(valid[i].sum()) > 0
    # The CUDA backend's method (Sionna's cfr), here on the CPU: the same channel, paths and delays.
    h_cfr, valid_cfr, tau_cfr = carrier_channels(paths, 3, radio.cfg.frequency_hz, method="cfr")
    assert h_cfr.dtype == np.complex64 and h_cfr.shape == h.shape
    np.testing.assert_allclose(h_cfr, h, rtol=0, atol=2e-6 * np.abs(cfr).max())
    np.testing.assert_array_equal(valid_cfr, valid)
    np.testing.assert_array_equal(tau_cfr, tau)
    with pytest.raises(ValueError, match="carrier method: expected one of auto, frozen, cfr, got 'fast'"):
        carrier_channels(paths, 3, radio.cfg.frequency_hz, method="fast")


def test_a_receivers_channel_does_not_depend_on_the_others(solved):
    _, links = solved
    alone = RadioScene(with_raytracing(RadioConfig, **FAST, uav_mesh=False), seed=2)
    alone.place({"b": UAVS["b"]})
    np.testing.assert_array_equal(alone.solve()["b"].h, links["b"].h)


def test_no_paths_give_a_zero_channel():
    radio = RadioScene(with_raytracing(RadioConfig, scene="empty", samples_per_src=1000, max_depth=1, threads=1,
                                       uav_mesh=False,
                                   shoot_cache=False, los=False), seed=1)
    radio.place({"a": UAVS["a"]})
    link = radio.solve()["a"]
    assert link.n_paths == 0 and link.path_gain == 0.0 and link.h.shape == (4, 64) and not link.los


def test_moved_bodies_share_one_geometry_update(monkeypatch):
    radio = RadioScene(with_raytracing(RadioConfig, **FAST, uav_mesh=True), seed=2)
    radio.place(UAVS)
    updates = []
    changed = rt_scene.geometry_changed
    monkeypatch.setattr(rt_scene, "geometry_changed", lambda scene: (updates.append(1), changed(scene)))
    moved = {k: p + [1.25, -0.5, 0.75] for k, p in UAVS.items()}
    radio.place(moved)
    assert len(updates) == 1
    for key, p in moved.items():
        np.testing.assert_allclose(np.array(radio.bodies[key].position).ravel(), p, atol=1e-4)
    radio.place(moved)  # nobody moved: no update
    assert len(updates) == 1
    # The vertices are those of Sionna's own setter, bit for bit.
    batched = {k: rt_scene.vertex_positions(radio.scene, b).copy() for k, b in radio.bodies.items()}
    for key, body in radio.bodies.items():
        body.position = (UAVS[key]).tolist()
        body.position = moved[key].tolist()
        np.testing.assert_array_equal(rt_scene.vertex_positions(radio.scene, body), batched[key])
