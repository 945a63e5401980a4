"""The ``protocol = "paper"`` switch (docs/paper-protocol.md): the 2023 link formula,
the hover and end rules of the 2023 flight, the image loss, the mission's use of the
previous step's throughput, parameter validation, and ``physical`` as the default."""

import dataclasses
import math

import numpy as np
import pytest
import tomllib

import caviar
from caviar_plugins import protocol as paper
from caviar_plugins.assets import DATA
from caviar_plugins.beam_selection.selector import BeamSelector
from caviar_plugins.mobility.frames import airsim_ned_to_scene
from caviar_plugins.mobility.waypoint_flight import PaperFlight, WaypointFlight, leg_distance
from caviar_plugins.mobility.waypoints import read_waypoints
from caviar_plugins.radio.beams import beam_gains, flat_dft_codebook
from caviar_plugins.radio.scene import normalize_channel
from caviar_plugins.radio.sionna_link import SionnaLinkParams
from caviar_plugins.sar.mission import Mission
from caviar_plugins.vision.image_link import ImageLink
from configs import episode, module, run_config
from conftest import ROOT, write_config

K_B = 1.380649e-23


def independent_rate_mbps(h: np.ndarray) -> np.ndarray:
    """The 2023 chain written out again with FFTs: H scaled to unit mean |H|²,
    G = Wr^H H Wt with unnormalised DFTs (Wt = 64-point over the Tx index: an FFT along
    axis 1; Wr^H = 4 · inverse FFT along axis 0), SNR = |G|² / (N_mW · I_mW) with
    N = k_B · 290 K · 40 MHz · (1 + 298.15/290) and I = +100 dBW."""
    h = h / np.sqrt(np.mean(np.abs(h) ** 2))
    g = 4 * np.fft.ifft(np.fft.fft(h, axis=1), axis=0)
    noise_mw = K_B * 290 * 40e6 * (1 + 298.15 / 290) * 1e3
    interference_mw = 1e10 * 1e3
    return 40e6 * np.log2(1 + np.abs(g) ** 2 / (noise_mw * interference_mw)) / 1e6


def plane_waves(n_paths: int, rng, spacing=paper.PAPER_SPACING) -> np.ndarray:
    """A (4, 64) channel of plane waves on the 2 x 2 and 8 x 8 arrays (Sionna element
    order k = row + rows * column, rows along z, columns along y)."""
    def steering(rows, cols, az, el):
        k = np.arange(rows * cols)
        z, y = -(k % rows) * spacing, (k // rows) * spacing
        return np.exp(2j * np.pi * (y * np.cos(el) * np.sin(az) + z * np.sin(el)))
    h = np.zeros((4, 64), complex)
    for _ in range(n_paths):
        a_r, a_t = rng.uniform(-np.pi, np.pi, 2), rng.uniform(-np.pi / 2, np.pi / 2, 2)
        gain = rng.normal() + 1j * rng.normal()
        h += gain * np.outer(steering(2, 2, a_r[0], a_t[0]), np.conj(steering(8, 8, a_r[1], a_t[1])))
    return h


def test_paper_rate_matches_an_independent_computation_and_ignores_distance():
    rng = np.random.default_rng(0)
    w_tx, w_rx = flat_dft_codebook(64), flat_dft_codebook(4)
    for n_paths in (1, 3, 10):
        h = plane_waves(n_paths, rng)
        ours = paper.paper_rate_mbps(beam_gains(normalize_channel(h), w_tx, w_rx))
        np.testing.assert_allclose(ours, independent_rate_mbps(h), rtol=1e-9)
        # Parseval: the mean pair gain of a unit-energy channel is exactly 4 · 64 = 256.
        assert beam_gains(normalize_channel(h), w_tx, w_rx).mean() == pytest.approx(256.0)
        # Path loss cancels: the same channel 120 dB weaker gives the same rates.
        np.testing.assert_allclose(paper.paper_rate_mbps(beam_gains(normalize_channel(1e-6 * h), w_tx, w_rx)),
                                   ours, rtol=1e-9)
    # The cap: a rank-1 channel aligned with one DFT pair gives |g|² = 4 · 64 · 256.
    h = np.outer(w_rx[:, 1], np.conj(w_tx[:, 5]))
    gains = beam_gains(normalize_channel(h), w_tx, w_rx)
    assert np.argmax(gains) == 1 * 64 + 5 and gains.max() == pytest.approx(65536.0)
    assert paper.paper_rate_mbps(gains.max()) == pytest.approx(176.18, abs=0.01)
    assert paper.PAPER_SNR_DIVISOR == pytest.approx(3248.11, abs=0.01)
    # No paths: H = 0 stays 0 and the rate is 0.
    assert paper.paper_rate_mbps(beam_gains(normalize_channel(np.zeros((4, 64))), w_tx, w_rx)).max() == 0.0


def sar_points():
    return airsim_ned_to_scene(read_waypoints(DATA / "central_park_path0.csv"))


def fly(flight: PaperFlight, requests: dict[int, float] | None = None, max_steps: int = 10_000) -> int:
    """Steps a PaperFlight like the plugin does; ``requests`` maps a step to a hover
    request made in that step. Returns the step at which it leaves its last waypoint."""
    requests = requests or {}
    for k in range(max_steps):
        if k in requests:
            flight.request_hover(requests[k])
        if flight.decide():
            return k
        flight.advance()
    raise AssertionError("the flight did not end")


def test_paper_flight_ends_on_leaving_waypoint_4_after_208_m():
    f = PaperFlight(sar_points(), 0.5, 5.0, 5.0, last=4)
    end = fly(f)
    assert f.target == 4 and f.flown_m == pytest.approx(208.33, abs=0.6)
    # 208.33 m at 5 m/s plus 1 s per stop-and-go leg, each arrival on the 0.5 s grid.
    assert 0.5 * end == pytest.approx(208.33 / 5 + 4, abs=2.0)
    assert leg_distance(20.0, 100.0, 5.0, 5.0) == 20.0 and leg_distance(2.0, 100.0, 5.0, 5.0) == 2.0


def test_paper_hover_is_served_at_the_next_waypoint_for_ceil_s_plus_one_steps():
    pts = np.array([[0.0, 0, 10], [20.0, 0, 10], [40.0, 0, 10], [60.0, 0, 10]])
    base = fly(PaperFlight(pts, 0.5, 5.0, 5.0, last=3))
    # A request at step 2 (on the way to waypoint 1) is served on arrival there:
    # ceil(2.6 / 0.5) = 6 steps of countdown, plus one: 3.5 s.
    f = PaperFlight(pts, 0.5, 5.0, 5.0, last=3)
    assert fly(f, {2: 2.6}) - base == 7 and f.hover_steps == 7
    # The last request before the arrival wins.
    assert fly(PaperFlight(pts, 0.5, 5.0, 5.0, last=3), {2: 2.6, 3: 0.9}) - base == 3
    # A request during the countdown is lost when the countdown ends.
    arrival = next(k for k in range(100) if _arrived_at(pts, 1, k))
    assert fly(PaperFlight(pts, 0.5, 5.0, 5.0, last=3), {2: 2.6, arrival + 2: 10.0}) - base == 7


def _arrived_at(pts, index, step) -> bool:
    f = PaperFlight(pts, 0.5, 5.0, 5.0, last=len(pts) - 1)
    for _ in range(step + 1):
        arrived = f.target == index and f.arrived()
        f.decide()
        f.advance()
    return arrived


def test_paper_flight_plugin_reports_the_mission_clock(tmp_path):
    log = run_config(tmp_path, episode(0.5, ["mobility"]) + module("uav", "mobility", "waypoint-flight", {
        "protocol": "paper", "waypoints": "central_park_path0.csv", "takeoff_s": 8.5}))
    end = log.topic(caviar.END_TOPIC).row(0, named=True)
    flight = PaperFlight(sar_points(), 0.5, 5.0, 5.0, last=4)
    assert end["flight_time_s"] == 0.5 * fly(flight)
    assert end["mission_time_s"] == pytest.approx(8.5 + end["flight_time_s"])
    assert end["flown_m"] == pytest.approx(208.33, abs=0.6)
    pos = log.topic("3D.mobility.positions")
    first = pos.row(0, named=True)["position"]
    assert (first["x"], first["y"], first["z"]) == pytest.approx((-297.0, 203.16, 9.23))


def test_paper_mission_uses_the_previous_throughput_and_skips_zero(tmp_path):
    log = run_config(tmp_path, episode(0.5, ["sensors", "mission"], steps=8)
                     + module("script", "sensors", "test_paper_protocol:ScriptedLink")
                     + module("mission", "mission", "mission", {"protocol": "paper"}))
    rescues = log.topic("mission.rescue")
    # Step 1 sees a person while the previous throughput was 0: nothing counted. Step 3
    # (previous step 40 Mbit/s, this step 80) counts with S = 320 Mbit / 40 Mbit/s.
    assert rescues["step"].to_list() == [3]
    assert rescues["hover_s"].to_list() == pytest.approx([8.0])
    result = log.topic("mission.result").row(0, named=True)
    assert result["rescued"] == 1 and result["mission_time_s"] == 61.5 and result["clock_offset_s"] == 8.5


class ScriptedLink(caviar.Plugin):
    """Throughput 0, 40, 40, 80, ... and the same person seen at steps 1, 3 and 4."""

    def step(self, t, inbox):
        k = self.ctx.step
        yield "communications.throughput", {"UE_type": "UAV", "UE_Id": "uav1",
                                            "throughput": [0.0, 40.0, 40.0, 80.0][min(k, 3)]}
        seen = [{"ground": {"x": 1.0, "y": 2.0}}] if k in (1, 3, 4) else []
        yield "ai.detections", {"UE_Id": "uav1", "count": len(seen), "detections": seen}
        if k == 5:
            yield caviar.END_TOPIC, {"reason": "script", "mission_time_s": 61.5, "clock_offset_s": 8.5}


def test_paper_image_loss_zeroes_exact_byte_counts_with_the_paper_psnr():
    rng = np.random.default_rng(5)
    image = rng.integers(60, 190, (120, 160, 3), dtype=np.uint8)
    mean_square = float(np.mean(image.astype(float) ** 2))
    for rate in (0.01, 0.25, 0.5):
        out = paper.zero_bytes(image, rate, np.random.default_rng(1))
        assert int(np.sum((out == 0) & (image != 0))) == int(image.size * rate)
        mse = float(np.mean((out.astype(float) - image) ** 2))
        assert mse == pytest.approx(rate * mean_square, rel=0.05)
    from caviar_plugins.vision.image_link import loss_for_throughput

    assert [loss_for_throughput(r, paper.PAPER_LOSS) for r in (150.0, 60.5, 60.0, 30.5, 30.0, 0.0)] == \
        [0.01, 0.01, 0.25, 0.25, 0.5, 0.5]


@pytest.mark.parametrize("params", [SionnaLinkParams, WaypointFlight.Params, Mission.Params, ImageLink.Params,
                                    BeamSelector.Params])
def test_protocol_is_validated_and_physical_is_the_default(params):
    extra = {"method": "random"} if params is BeamSelector.Params else {}
    assert params(**extra).protocol == "physical"
    with pytest.raises(ValueError, match=r"protocol: expected one of 'physical', 'paper', got 'papers'"):
        params(protocol="papers", **extra)


def test_config_error_names_the_module_and_key(tmp_path):
    cfg = write_config(tmp_path, episode(0.5, ["mobility"]) + module("uav", "mobility", "waypoint-flight",
                                                                     {"protocol": "2023"}))
    with pytest.raises(caviar.ConfigError, match=r"exp.toml:8: modules.uav.params.protocol: expected one of"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")


def test_paper_link_fixes_the_2023_settings():
    from caviar_plugins.radio.scene import radio_config
    from caviar_plugins.rt.settings import TraceSettings

    p = SionnaLinkParams(protocol="paper", spacing=0.5, raytracing=TraceSettings(los=True))  # (their defaults)
    r = radio_config(p)
    rays = r.raytracing
    assert r.spacing == pytest.approx(5.7142857) and not rays.los and r.normalize and r.codebook == "flat-dft"
    assert not rays.refraction and not rays.diffuse_reflection and r.antenna_offset == [0.35, 0.069, -8.23]
    assert rays.specular_reflection and rays.diffraction
    d = SionnaLinkParams()
    assert d.spacing == 0.5 and d.raytracing.los and not d.normalize and d.codebook == "kronecker"
    assert d.antenna_offset == [0.0, 0.0, 1.5]


def test_the_paper_preset_refuses_a_key_the_user_set_to_another_value(tmp_path):
    """``protocol = "paper"`` sets 12 fields; one the configuration wrote with another value
    is refused by its key path, not overridden silently. The same value is fine."""
    cfg = tmp_path / "exp.toml"
    head = ('[episode]\nts = 0.5\nsteps = 1\nstages = ["c"]\n[modules.comm]\nstage = "c"\n'
            'plugin = "sionna-link"\n')
    cfg.write_text(head + 'params = { protocol = "paper", raytracing = { los = true, samples_per_src = 1000 } }\n')
    with pytest.raises(caviar.ConfigError, match=r"exp.toml:\d+: modules.comm.params.raytracing.los: protocol = "
                                                 r"'paper' sets it to False; the configuration gives True"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    with pytest.raises(ValueError, match=r"spacing: protocol = 'paper' sets it to 5.71"):
        SionnaLinkParams(protocol="paper", spacing=1.0)  # (built in Python: differs from default and preset)
    from caviar._host import check_params
    from caviar_plugins.radio.sionna_link import SionnaLink

    p = check_params(SionnaLink, {"protocol": "paper", "raytracing": {"los": False}, "codebook": "flat-dft"})
    assert p.codebook == "flat-dft" and not p.raytracing.los and p.normalize


def test_blueprints_set_the_protocol_where_they_should():
    physical = tomllib.loads((ROOT / "blueprints" / "sar" / "config.toml").read_text())
    assert all("protocol" not in m.get("params", {}) for m in physical["modules"].values())
    paper_bp = tomllib.loads((ROOT / "blueprints" / "sar-paper" / "config.toml").read_text())
    for name in ("uav", "beams", "comm", "link", "mission"):
        assert paper_bp["modules"][name]["params"]["protocol"] == "paper", name
    for f in ("paper.toml", "paper-test-flight.toml"):
        bp = tomllib.loads((ROOT / "blueprints" / "beam-dataset" / f).read_text())
        assert {bp["modules"][m]["params"]["protocol"] for m in ("uav", "comm")} == {"paper"}
    assert dataclasses.fields(SionnaLinkParams)  # imported for the defaults above
    assert math.isclose(paper.PAPER_SPACING, 0.5 * 40 / 3.5)


def test_paper_top_k_counts_the_predicted_pair_among_the_k_strongest():
    from caviar_plugins.tools.baselines.paper_topk import hits

    gains = np.array([[0.0, 5, 3, 1], [4.0, 4, 1, 0]])
    # Row 0 ranks 1, 2, 3, 0; row 1 ranks 0, 1 (tie: lower index first), 2, 3.
    assert hits(np.array([2, 1]), gains, ks=(1, 2, 4)) == {1: 0.0, 2: 1.0, 4: 1.0}
    assert hits(np.array([1, 0]), gains, ks=(1,)) == {1: 1.0}


def test_gain_knn_picks_the_pair_strong_around_a_position():
    from caviar_plugins.beam_selection.knn import GainKNN

    pos = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [50, 0, 0]])
    gains = np.array([[1.0, 0.9, 0], [0.0, 1, 0.2], [0.1, 1, 0], [0, 0, 1]])
    model = GainKNN(k=3).fit(pos, gains)
    # The best pair flips near x = 0..2, but pair 1 is strong at all three: k-NN picks it.
    assert model.predict(np.array([[1.0, 0.5, 0]])).tolist() == [1]
    assert model.predict(np.array([[49.0, 0, 0]])).tolist() == [2]  # distance weights: x = 50 dominates
    assert GainKNN(k=3, weights="uniform").fit(pos, gains).predict(np.array([[49.0, 0, 0]])).tolist() == [1]
    assert GainKNN(k=1).fit(pos, gains).predict(np.array([[49.0, 0, 0]])).tolist() == [2]


def test_sweep_forest_uses_the_previous_sweep():
    from caviar_plugins.beam_selection.knn import SweepForest

    rng = np.random.default_rng(2)
    pos = rng.uniform(0, 1, (200, 3))
    prev = rng.uniform(0, 1, (200, 256))
    best = np.argmax(prev, axis=1) % 4  # the label depends only on the previous sweep
    model = SweepForest(n_estimators=50).fit(pos, prev, best)
    assert SweepForest.features(pos[:3], None).shape == (3, 259)
    assert np.mean(model.predict(pos, prev) == best) == 1.0
    assert model.predict(pos[:2]).shape == (2,)  # first step: no sweep yet


def test_near_forest_far_previous_switches_at_the_radius():
    """Within the radius of a training position: the forest's pair (here a fixed label the
    sweep does not predict); beyond: the previous sweep's best; no sweep: the forest."""
    from caviar_plugins.beam_selection.knn import NearForestFarPrevious

    rng = np.random.default_rng(3)
    pos = np.c_[rng.uniform(0, 10, 300), np.zeros((300, 2))]  # a street along x
    prev = rng.uniform(0, 1, (300, 256))
    best = np.full(300, 7)
    model = NearForestFarPrevious(radius_m=1.0, n_estimators=20).fit(pos, prev, best)
    query_prev = np.zeros((4, 256))
    query_prev[:, 200] = 1.0
    query = np.array([[5.0, 0.5, 0], [5.0, 0.99, 0], [5.0, 1.01, 0], [5.0, 30.0, 0]])
    np.testing.assert_allclose(model.distance_m(query), [0.5, 0.99, 1.01, 30.0], atol=0.05)
    assert model.predict(query, query_prev).tolist() == [7, 7, 200, 200]
    assert model.predict(query).tolist() == [7, 7, 7, 7]  # first step: no sweep
    assert model.predict(query, np.zeros((4, 256))).tolist() == [7, 7, 7, 7]  # a sweep without paths


def test_the_near_far_radius_is_chosen_on_the_training_flights_only():
    """near_far_lofo scores every radius by leaving each training flight out; the test flight
    never enters it (its signature has no place for it)."""
    import inspect

    from caviar_plugins.tools.baselines.paper_topk import RADII_M, near_far_lofo

    assert list(inspect.signature(near_far_lofo).parameters) == ["parts", "radii"]
    rng = np.random.default_rng(4)
    parts = []
    for k in range(3):  # three flights on parallel lines 3 m apart; the best pair follows the sweep
        prev = rng.uniform(0, 1, (40, 256))
        x = np.c_[np.linspace(0, 20, 40), np.full(40, 3.0 * k), np.zeros(40)]
        parts.append({"position": x, "previous_gains": prev, "best_pair": np.argmax(prev, axis=1),
                      "gains": np.eye(256)[np.argmax(prev, axis=1)] + 0.01})
    scores = near_far_lofo(parts)
    assert set(scores) == set(RADII_M)
    # Left-out flights lie 3 m from the others: every radius below 3 m uses the previous sweep there,
    # which is right by construction here.
    assert all(v == 1.0 for v in scores.values()), scores
