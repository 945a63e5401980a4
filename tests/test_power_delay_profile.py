"""Power-delay profiles among the measurements (issue #56, part 1): the taps read from CSV,
Parquet and a topic, bad taps named with their row and field, the RMS delay spread against a
hand computation, and the spread the twin predicts from traced paths against the geometry of
one metal plate (Sionna's ``simple_reflector``: the line of sight and one reflection, whose
delays the image method gives and whose powers Friis and a perfect reflector give)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from caviar_plugins.twin.measurements import (
    FIELDS,
    MeasurementError,
    from_messages,
    from_rows,
    read_measurements,
    rms_delay_spread,
)

F = 3.5e9
C = 299_792_458.0


def _row(**changes):
    row = {"time_s": 0.0, "rx_x": 1.0, "rx_y": 2.0, "rx_z": 1.5, "tx_x": 0.0, "tx_y": 0.0, "tx_z": 10.0,
           "power_dbm": -70.0, "tx_power_dbm": 30.0, "frequency_hz": F, "bandwidth_hz": 20e6}
    row.update(changes)
    return row


def test_the_rms_delay_spread_is_the_hand_computation():
    # two equal taps 100 ns apart: ±50 ns about their mean
    assert rms_delay_spread(np.array([0.0, 100e-9]), np.array([1.0, 1.0]), 1e-9) == pytest.approx(50e-9, rel=1e-9)
    # three taps, powers 1, 0.5, 0.25 at 0, 100, 300 ns (binned at 1 ns, each at its bin's centre: a shift)
    p, t = np.array([1.0, 0.5, 0.25]), np.array([0.0, 100e-9, 300e-9])
    mean = (p * t).sum() / p.sum()
    hand = math.sqrt((p * (t - mean) ** 2).sum() / p.sum())
    assert rms_delay_spread(t + 7e-6, p, 1e-9) == pytest.approx(hand, rel=1e-9)  # the origin does not count
    # at a sounder's 50 ns (20 MHz), taps 10 ns apart fall in one bin: no spread
    assert rms_delay_spread(np.array([0.0, 10e-9]), np.array([1.0, 1.0]), 50e-9) == 0.0
    assert math.isnan(rms_delay_spread(np.array([0.0]), np.array([0.0]), 1e-9))
    # delays written in ns by mistake span 2.4e9 bins of 50 ns: only the bins with taps are made
    assert rms_delay_spread(np.array([0.0, 50.0, 120.0]), np.ones(3), 50e-9) > 40.0


def test_profiles_round_trip_through_csv_parquet_and_a_topic(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = [(f"r{i}", _row(time_s=float(i), pdp_delay_s=[0.0, 50e-9 * (i + 1)], pdp_power_dbm=[-70.0, -80.0 - i]))
            for i in range(3)] + [("r3", _row(time_s=3.0))]  # the last one without a profile
    data = from_rows(rows, "test")
    expected = [rms_delay_spread(np.array([0.0, 50e-9 * (i + 1)]), 10 ** (np.array([-70.0, -80.0 - i]) / 10), 50e-9)
                for i in range(3)]
    back = read_measurements(data.write_csv(tmp_path / "m.csv"))
    spread = back.delay_spread_s()
    np.testing.assert_allclose(spread[:3], expected, rtol=1e-12)
    assert np.isnan(spread[3]) and expected[2] > expected[0] > 0
    pq.write_table(pa.Table.from_pylist(data.rows()), tmp_path / "m.parquet")
    np.testing.assert_allclose(read_measurements(tmp_path / "m.parquet").delay_spread_s()[:3], expected, rtol=1e-12)

    class M:
        topic, step = "measurements.uav1", 2

        def __init__(self, d):
            self.data = d

    as_arrays = {k: np.asarray(v) if isinstance(v, list) else v for k, v in data.rows()[0].items()}
    np.testing.assert_allclose(from_messages([M(as_arrays)]).delay_spread_s(), expected[:1], rtol=1e-12)
    with pytest.raises(MeasurementError, match=r"r tap 0: field 'pdp_power_dbm': expected a number, got '-70,5'"):
        from_rows([("r", _row(pdp_delay_s="0;1e-7", pdp_power_dbm="-70,5;-80"))], "test")  # a decimal comma
    with pytest.raises(MeasurementError, match="pdp: 3 profiles for 4 samples"):
        dataclasses.replace(data, pdp=data.pdp[:3])  # type: ignore[index]
    joined = from_messages([M({"samples": data.rows()[:2]}), M(data.rows()[3])])
    np.testing.assert_allclose(joined.delay_spread_s()[:2], expected[:2], rtol=1e-12)
    assert np.isnan(joined.delay_spread_s()[2])
    assert np.array_equal(joined.subset(np.array([False, True, True])).delay_spread_s()[:1], expected[1:2])


@pytest.mark.parametrize("changes, named", [
    ({"pdp_delay_s": "0;1e-7"}, "field 'pdp_power_dbm' is missing"),
    ({"pdp_delay_s": "0;1e-7", "pdp_power_dbm": "-70"}, "field 'pdp_power_dbm': 1 taps, but 'pdp_delay_s' has 2"),
    ({"pdp_delay_s": "-1e-9", "pdp_power_dbm": "-70"}, "tap 0: field 'pdp_delay_s': expected delays >= 0"),
    ({"pdp_delay_s": "0;soon", "pdp_power_dbm": "-70;-80"},
     "tap 1: field 'pdp_delay_s': expected a number, got 'soon'"),
    ({"pdp_delay_s": "0", "pdp_power_dbm": "nan"}, "field 'pdp_power_dbm': expected a finite number"),
])
def test_bad_taps_are_named_with_their_row_and_field(tmp_path, changes, named):
    path = tmp_path / "m.csv"
    fields = [*FIELDS, "pdp_delay_s", "pdp_power_dbm"]
    rows = [_row(), _row(**changes)]
    path.write_text(",".join(fields) + "\n" + "\n".join(",".join(str(r.get(f, "")) for f in fields) for r in rows))
    with pytest.raises(MeasurementError) as e:
        read_measurements(path)
    assert f"{path} row 2 (line 3)" in str(e.value) and named in str(e.value)


@pytest.mark.parametrize("reuse", [True, False])
def test_the_predicted_spread_of_a_plate_is_the_image_methods(reuse):
    """A metal plate in z = 0 (1 m square), a transmitter and receivers above it: two paths,
    the line of sight (d1) and the reflection (d2, from the transmitter's image below the
    plate). With vertical polarisation in the plane of incidence and a perfect conductor, the
    powers are Friis's (λ/4πd)², so the spread is Δτ·√(p1·p2)/(p1 + p2) with Δτ = (d2 − d1)/c."""
    from caviar_plugins.rt.received_power import ReceivedPower
    from caviar_plugins.rt.scene import sionna_rt
    from caviar_plugins.twin.fit import FIT_RAYS

    rt = sionna_rt()
    scene = rt.load_scene(rt.scene.simple_reflector)
    scene.frequency = F
    tx = np.array([-0.4, 0.0, 1.0])
    rx = np.array([[0.4, 0.0, 1.0], [0.3, 0.0, 0.6], [0.2, 0.0, 1.5]])  # reflections at x within the plate
    rays = dataclasses.replace(FIT_RAYS, samples_per_src=100_000, max_depth=1, threads=1)
    model = ReceivedPower(scene, rays, seed=0, reuse_geometry=reuse)
    model.place(rx, tx[None])
    got = model.delay_spreads(np.c_[np.arange(3), np.zeros(3, dtype=int)], 1e-13)
    image = tx * [1, 1, -1]
    for i, r in enumerate(rx):
        d1, d2 = np.linalg.norm(r - tx), np.linalg.norm(r - image)
        p1, p2 = d1**-2, d2**-2
        hand = (d2 - d1) / C * math.sqrt(p1 * p2) / (p1 + p2)
        assert got[i] == pytest.approx(hand, rel=0.01), (i, got[i], hand)


def test_a_fit_reports_the_delay_spread_it_never_descended_on(tmp_path):
    """The street canyon with concrete 3x its scene value, measured with 0.3 dB of noise on the
    power and a profile at 200 MHz (5 ns taps) per sample: fitting the power alone brings the
    predicted delay spread to the measured one, on the fitted and the held-out samples."""
    from caviar_plugins.rt.materials import apply_materials
    from caviar_plugins.rt.received_power import ReceivedPower
    from caviar_plugins.rt.scene import sionna_rt
    from caviar_plugins.twin.fit import FIT_RAYS, FitSettings, fit_materials
    from caviar_plugins.twin.measurements import Measurements

    rt = sionna_rt()
    rays = dataclasses.replace(FIT_RAYS, los=False, max_depth=2, samples_per_src=20_000, threads=1)
    tx, n, bandwidth = np.array([-40.0, 0.0, 12.0]), 24, 200e6

    def street():
        scene = rt.load_scene(rt.scene.simple_street_canyon)
        scene.frequency = F
        return scene

    rng = np.random.default_rng(5)
    rx = np.c_[rng.uniform(-55, 55, n), rng.uniform(-8, 8, n), np.full(n, 1.5)]
    truth = street()
    model = ReceivedPower(truth, rays, seed=0)
    apply_materials(truth, {"concrete": {"relative_permittivity": 3 * 5.24}})
    model.place(rx, tx[None])
    pairs = np.c_[np.arange(n), np.zeros(n, dtype=int)]
    power = model.predict(pairs, 30.0) + np.random.default_rng(1).normal(0.0, 0.3, n)
    profiles = model.power_delay_profiles(pairs, 1 / bandwidth)
    assert all(p is not None for p in profiles)
    pdp = [(t, 30.0 + 10 * np.log10(g)) for t, g in profiles]  # type: ignore[misc]
    data = Measurements(np.arange(n, dtype=float), rx, np.tile(tx, (n, 1)), power, np.full(n, 30.0), F, bandwidth,
                        pdp)
    settings = FitSettings(learn=("relative_permittivity",), materials=("concrete",), iterations=10, holdout=0.25,
                           noise_db=0.3, search_sweeps=1, restarts=0, rival_starts=0)
    result = fit_materials(street(), data, settings, rays)
    ds = result.delay_spread_ns
    assert ds["samples"] == n and ds["measured_median"] > 2.5  # more than half a tap
    assert ds["fit"]["after"] < 0.3 * ds["fit"]["before"], ds
    assert ds["held_out"]["after"] < 0.5 * ds["held_out"]["before"], ds
    assert "delay_spread_ns" in result.as_json()
    assert np.isfinite(result.delay_spread_s["after"]).all()
    from caviar_plugins.tools.fit_scene.report import plot_fit

    assert plot_fit(result, data, tmp_path / "fit.png").stat().st_size > 10_000  # with the spread's panel
