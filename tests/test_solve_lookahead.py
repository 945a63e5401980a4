"""Look-ahead ray tracing with the UAV bodies (issue #53): one solve traces a UAV's
forecast positions, each with a body of its own, and its links agree with solving step by
step; the look-ahead depth by backend; bad settings name their key."""

import numpy as np
import pytest

from caviar_plugins.rt import configure_drjit

configure_drjit()

from caviar_plugins import DATA  # noqa: E402
from caviar_plugins.mobility import Path, read_waypoints  # noqa: E402
from caviar_plugins.radio import RadioConfig, RadioScene, SionnaLinkParams  # noqa: E402
from caviar_plugins.radio.scene import LookaheadTracer, lookahead_depth  # noqa: E402
from caviar_plugins.rt.scene import OUT_OF_THE_WAY_M  # noqa: E402
from caviar_plugins.rt.settings import with_raytracing  # noqa: E402

FAST = dict(samples_per_src=20_000, max_depth=3, uav_mesh=True, threads=1)
ROUTE = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))

GAIN_TOLERANCE_DB = 0.5
"""Path gain of a look-ahead link against the step-by-step solve. The other slots' bodies
(the UAV 2.5 m and more along its route, below its antenna) block or add a few paths:
measured up to 0.30 dB (one path fewer) on the SAR route at 2e4 samples."""


def step_by_step(points) -> list:
    radio = RadioScene(with_raytracing(RadioConfig, **FAST), seed=3)
    out = []
    for p in points:
        radio.place({"uav1": p})
        out.append(radio.solve()["uav1"])
    return out


@pytest.mark.parametrize("start", [10.0, 60.0])
def test_lookahead_with_uav_bodies_agrees_with_step_by_step(start):
    points = [ROUTE.at(start + 2.5 * k) for k in range(5)]  # 5 m/s, Ts = 0.5 s
    tracer = LookaheadTracer(RadioScene(with_raytracing(RadioConfig, **FAST), seed=3), steps=4)
    ahead = [tracer.links({"uav1": points[0]}, {"uav1": points[1:]})["uav1"]]
    ahead += [tracer.links({"uav1": p}, {})["uav1"] for p in points[1:]]
    assert tracer.solves == 1 and tracer.hits == 4
    for a, b in zip(ahead, step_by_step(points), strict=True):
        assert a.best_pair == b.best_pair
        assert abs(10 * np.log10(a.path_gain / b.path_gain)) < GAIN_TOLERANCE_DB
        assert abs(10 * np.log10(a.gains.max() / b.gains.max())) < 0.1
        assert abs(a.n_paths - b.n_paths) <= 2 and a.los == b.los


def test_a_hovering_uav_parks_its_extra_bodies_and_matches_step_by_step():
    p = ROUTE.at(60.0)
    radio = RadioScene(with_raytracing(RadioConfig, **FAST), seed=3)
    tracer = LookaheadTracer(radio, steps=3)
    link = tracer.links({"uav1": p}, {"uav1": [p, p, p]})["uav1"]
    z = [float(np.array(radio.bodies[f"uav1@{k}"].position).ravel()[2]) for k in range(4)]
    assert z[0] == pytest.approx(p[2], abs=1e-3)
    assert all(h == pytest.approx(p[2] - OUT_OF_THE_WAY_M, abs=1e-2) for h in z[1:])
    assert radio.movers.rays_at(radio.bodies["uav1@1"]) == 0 and radio.movers.rays_at(radio.bodies["uav1@0"])
    ref = step_by_step([p])[0]
    assert link.best_pair == ref.best_pair and link.n_paths == ref.n_paths
    assert abs(10 * np.log10(link.path_gain / ref.path_gain)) < 1e-3
    # The UAV flies on: its parked bodies come back under their receivers.
    q = ROUTE.at(62.5)
    tracer.links({"uav1": q}, {"uav1": [ROUTE.at(62.5 + 2.5 * k) for k in (1, 2, 3)]})
    assert float(np.array(radio.bodies["uav1@1"].position).ravel()[2]) == pytest.approx(
        ROUTE.at(65.0)[2], abs=1e-3)
    assert radio.movers.rays_at(radio.bodies["uav1@1"]) != 0


def test_lookahead_depth_by_backend():
    assert lookahead_depth(3, 10, "cuda_ad_mono_polarized") == 3
    assert lookahead_depth("auto", 1, "cuda_ad_mono_polarized") == 9
    assert lookahead_depth("auto", 10, "cuda_ad_mono_polarized") == 3
    assert lookahead_depth("auto", 1, "llvm_ad_mono_polarized") == 9
    assert lookahead_depth("auto", 10, "llvm_ad_mono_polarized") == 2
    assert lookahead_depth("auto", 100, "llvm_ad_mono_polarized") == 1


@pytest.mark.parametrize("changes, key", [
    ({"lookahead_steps": -1}, "lookahead_steps"), ({"lookahead_steps": "deep"}, "lookahead_steps"),
    ({"lookahead_steps": 2.5}, "lookahead_steps"), ({"lookahead": "yes"}, "lookahead"),
    ({"cache_tolerance_m": -0.1}, "cache_tolerance_m")])
def test_bad_lookahead_settings_name_their_key(changes, key):
    with pytest.raises(ValueError, match=f"^{key}: expected"):
        SionnaLinkParams(**{"lookahead": True, **changes})


def test_lookahead_with_uav_bodies_is_accepted():
    params = SionnaLinkParams(lookahead=True, uav_mesh=True)
    assert params.lookahead_steps == "auto"


def test_lookahead_with_uav_bodies_is_deterministic():
    points = [ROUTE.at(100.0 + 2.5 * k) for k in range(3)]
    runs = []
    for _ in range(2):
        tracer = LookaheadTracer(RadioScene(with_raytracing(RadioConfig, **FAST), seed=5), steps=2)
        runs.append([tracer.links({"uav1": points[0]}, {"uav1": points[1:]})["uav1"]] +
                    [tracer.links({"uav1": p}, {})["uav1"] for p in points[1:]])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a.h, b.h)
        assert a.n_paths == b.n_paths and a.best_pair == b.best_pair


def test_lookahead_with_uav_bodies_resumes_to_the_same_messages(tmp_path, cli):
    """A run killed and resumed records what the uninterrupted one did: the look-ahead's
    traces and slots are in the checkpoint, the parked bodies come back on its next solve."""
    from test_resume_plugins import BLUEPRINTS, _resumes_to_the_reference

    sets = ["--set", "modules.comm.params.raytracing.samples_per_src=10000", "--set",
            "modules.comm.params.raytracing.threads=1",
            "--set", "modules.comm.params.uav_mesh=true", "--set", "modules.comm.params.lookahead=true",
            "--set", "modules.comm.params.lookahead_steps=2", "--set", "modules.uav.params.forecast_steps=2"]
    log = _resumes_to_the_reference(tmp_path, cli, BLUEPRINTS / "raytraced" / "config.toml", sets, 5, every=3,
                                    steps=11)
    assert len(log.topic("3D.mobility.forecast")) == 11
