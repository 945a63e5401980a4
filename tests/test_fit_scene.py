"""The self-calibrating twin (issue #56): measurements as data, the gradient of received power
with respect to a material through Sionna RT against a finite difference, a fit that finds
known materials back from noisy synthetic measurements, what cannot be identified, the
calibrated scene file, ``caviar-core fit-scene``'s flags, and the loop in a run.

The scene is Sionna's ``simple_street_canyon`` (five materials on seven buildings), traced
without the line of sight so that every path's power depends on a wall: 16 receivers, 2e4
rays, depth 2 (under a second a solve on the 2-core machine)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from caviar_plugins.twin.fit import FIT_RAYS, FitSettings, fit_materials
from caviar_plugins.twin.measurements import FIELDS, MeasurementError, Measurements, from_rows, read_measurements
from caviar_plugins.twin.search import coarse_search, from_log, rmse, search_grid, to_log

ROOT = pathlib.Path(__file__).resolve().parents[1]
RAYS = dataclasses.replace(FIT_RAYS, los=False, max_depth=2, samples_per_src=20_000, threads=1)
TX = [-40.0, 0.0, 12.0]
F = 3.5e9


def _street(rt):
    scene = rt.load_scene(rt.scene.simple_street_canyon)
    scene.frequency = F
    return scene


def _receivers(n=16, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-55, 55, n), rng.uniform(-8, 8, n), np.full(n, 1.5)]


@pytest.fixture(scope="module")
def rt():
    from caviar_plugins.rt.scene import sionna_rt

    return sionna_rt()


def _measure(rt, truth, rx, noise_db=0.5, seed=1):
    """Synthetic measurements: the street traced with ``truth`` materials, plus noise."""
    from caviar_plugins.rt.materials import apply_materials
    from caviar_plugins.rt.received_power import ReceivedPower

    scene = _street(rt)
    model = ReceivedPower(scene, RAYS, seed=0)
    apply_materials(scene, truth)
    model.place(rx, np.array([TX]))
    p = model.predict(np.stack([np.arange(len(rx)), np.zeros(len(rx), dtype=int)], axis=1), 30.0)
    assert np.isfinite(p).all(), "every receiver sees a reflected path"
    noise = np.random.default_rng(seed).normal(0.0, noise_db, len(rx))
    n = len(rx)
    return Measurements(np.arange(n, dtype=float), rx, np.tile(TX, (n, 1)), p + noise, np.full(n, 30.0), F, 20e6)


# -- measurements as data ------------------------------------------------------------------

def _row(**changes):
    row = {"time_s": 0.0, "rx_x": 1.0, "rx_y": 2.0, "rx_z": 1.5, "tx_x": 0.0, "tx_y": 0.0, "tx_z": 10.0,
           "power_dbm": -70.0, "tx_power_dbm": 30.0, "frequency_hz": F, "bandwidth_hz": 20e6}
    row.update(changes)
    return row


def test_measurements_round_trip_through_csv(tmp_path):
    data = from_rows([(f"r{i}", _row(time_s=float(i), power_dbm=-70.0 - i)) for i in range(5)], "test")
    back = read_measurements(data.write_csv(tmp_path / "m.csv"))
    assert len(back) == 5 and back.frequency_hz == F
    np.testing.assert_array_equal(back.power_dbm, [-70, -71, -72, -73, -74])
    np.testing.assert_array_equal(back.rx[2], [1.0, 2.0, 1.5])


@pytest.mark.parametrize("row, named", [
    (_row(power_dbm="strong"), "field 'power_dbm': expected a number"),
    (_row(rx_z=float("nan")), "field 'rx_z': expected a finite number"),
    (_row(frequency_hz=-1.0), "field 'frequency_hz': expected a number > 0"),
    ({k: v for k, v in _row().items() if k != "tx_y"}, "field 'tx_y' is missing"),
    (_row(bandwidth_hz=10e6), "field 'bandwidth_hz': 1e+07 differs"),
])
def test_a_bad_row_is_named_with_its_field(tmp_path, row, named):
    path = tmp_path / "m.csv"
    rows = [_row(), row]
    fields = list(dict.fromkeys([*FIELDS, *row]))
    path.write_text(",".join(fields) + "\n" + "\n".join(",".join(str(r.get(f, "")) for f in fields) for r in rows))
    with pytest.raises(MeasurementError) as e:
        read_measurements(path)
    assert f"{path} row 2 (line 3)" in str(e.value) and named in str(e.value)


def test_an_unknown_column_is_named(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(",".join([*FIELDS, "rsrp"]) + "\n" + ",".join(["1"] * (len(FIELDS) + 1)) + "\n")
    with pytest.raises(MeasurementError, match=r"m.csv line 1: unknown column 'rsrp'"):
        read_measurements(path)


def test_measurements_from_a_topic_name_the_topic_and_step():
    from caviar_plugins.twin.measurements import from_messages

    class M:
        def __init__(self, data, step):
            self.topic, self.data, self.step = "measurements.uav1", data, step

    data = from_messages([M(_row(), 0), M({"samples": [_row(), _row(time_s=1.0)]}, 1)])
    assert len(data) == 3
    with pytest.raises(MeasurementError, match=r"topic measurements.uav1 \(step 4\) sample 1: field 'rx_x'"):
        from_messages([M({"samples": [_row(), _row(rx_x="here")]}, 4)])


# -- physics: the gradient and the fit ------------------------------------------------------

def test_gradient_of_received_power_matches_a_finite_difference(rt):
    """d(MSE in dB)/d(ε_r) from Dr.Jit through Sionna's field computation against a central
    difference of the same loss computed from plain predictions."""
    from caviar_plugins.rt.received_power import ReceivedPower

    data = _measure(rt, {"marble": {"relative_permittivity": 14.0}}, _receivers(10))
    scene = _street(rt)
    model = ReceivedPower(scene, RAYS, seed=0)
    model.place(data.rx, np.array([TX]))
    pairs = np.stack([np.arange(len(data)), np.zeros(len(data), dtype=int)], axis=1)
    w = np.ones(len(data))
    for material in ("marble", "concrete"):
        key = (material, "relative_permittivity")
        eps = 7.0
        _, loss, grads = model.loss_and_gradient(pairs, 30.0, data.power_dbm, w, {key: eps})
        h = 0.02

        def mse(v, key=key):
            return float(np.mean((model.predict(pairs, 30.0, {key: v}) - data.power_dbm) ** 2))

        fd = (mse(eps + h) - mse(eps - h)) / (2 * h)
        assert abs(grads[key]) > 0.05, f"{material}: the measurements see it"
        assert grads[key] == pytest.approx(fd, rel=0.05, abs=0.02), material
        model.predict(pairs, 30.0, {key: eps if material == "marble" else 5.24})


def test_paths_traced_once_give_a_whole_solves_powers_and_gradients(rt):
    """A fit traces once per placement and computes only the fields for each guess
    (``reuse_geometry``): at other materials, its dBm and its gradient equal a whole solve's
    with the same seed, pair by pair (two transmitters, the line of sight on); with diffuse
    reflection, whose sampling depends on the materials, it is refused."""
    from caviar_plugins.rt.received_power import ReceivedPower

    rx = _receivers(12, seed=3)
    sites = np.array([TX, [40.0, 3.0, 20.0]])
    pairs = np.array([[i, i % 2] for i in range(len(rx))])
    rays = dataclasses.replace(RAYS, los=True, max_depth=3)
    models = []
    for reuse in (True, False):
        model = ReceivedPower(_street(rt), rays, seed=0, reuse_geometry=reuse)
        model.place(rx, sites)
        models.append(model)
    once, whole = models
    measured = whole.predict(pairs, 30.0, {("concrete", "relative_permittivity"): 15.0}) + 0.5
    for values in ({("concrete", "relative_permittivity"): 15.0, ("glass", "conductivity"): 0.3},
                   {("concrete", "relative_permittivity"): 3.0, ("marble", "relative_permittivity"): 20.0}):
        a, b = once.predict(pairs, 30.0, values), whole.predict(pairs, 30.0, values)
        assert np.array_equal(np.isfinite(a), np.isfinite(b)) and np.isfinite(b).sum() >= 10
        np.testing.assert_allclose(a[np.isfinite(b)], b[np.isfinite(b)], atol=1e-4)
        _, loss_a, grad_a = once.loss_and_gradient(pairs, 30.0, measured, np.ones(len(rx)), values)
        _, loss_b, grad_b = whole.loss_and_gradient(pairs, 30.0, measured, np.ones(len(rx)), values)
        assert loss_a == pytest.approx(loss_b, rel=1e-5)
        for key in values:
            assert grad_a[key] == pytest.approx(grad_b[key], rel=1e-3, abs=1e-7), key
    assert once.solves == 1 and once.field_evaluations == 4 and whole.solves == 5
    with pytest.raises(ValueError, match="reuse_geometry: a diffuse bounce"):
        ReceivedPower(_street(rt), dataclasses.replace(rays, diffuse_reflection=True), reuse_geometry=True)
    assert not ReceivedPower(_street(rt), dataclasses.replace(rays, diffuse_reflection=True)).reuse_geometry


def test_a_receivers_power_does_not_depend_on_the_receivers_traced_with_it(rt, monkeypatch):
    """Sionna drops a (specular chain, receiver) pair whose slot in its table of chains seen
    another pair took: with many receivers in one trace, which pairs are lost depends on the
    others (on osm-city, 500 receivers and 2e5 rays lost 23 % of the paths, up to 19 dB on one
    receiver). A table shrunk to the path buffer (8,000 slots for about 1,200 pairs) makes that
    happen here: not allowed to grow it, the trace warns, and 30 receivers' powers change when
    30 more are traced with them; allowed, it traces again with a larger table and they do not."""
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    from caviar_plugins.rt import sionna_adapter
    from caviar_plugins.rt.received_power import ReceivedPower

    rx = _receivers(60, seed=5)
    rays = dataclasses.replace(RAYS, max_num_paths_per_src=8_000)
    monkeypatch.setattr(SBCandidateGenerator, "MIN_SPEC_COUNT_SIZE", 1)

    def first_30(n: int) -> tuple[np.ndarray, ReceivedPower]:
        model = ReceivedPower(_street(rt), rays, seed=0)
        model.place(rx[:n], np.array([TX]))
        return model.predict(np.stack([np.arange(30), np.zeros(30, dtype=int)], axis=1), 30.0), model

    monkeypatch.setattr(sionna_adapter, "MAX_CHAIN_SLOTS", 1)  # not allowed to grow
    with pytest.warns(RuntimeWarning, match="lost to collisions"):
        alone, lossy = first_30(30)
        crowded, _ = first_30(60)
    assert lossy.chain_loss > 0.05 and lossy.solves == 1
    assert np.nanmax(np.abs(alone - crowded)) > 0.5
    monkeypatch.setattr(sionna_adapter, "MAX_CHAIN_SLOTS", 1 << 26)
    alone, model = first_30(30)
    crowded, crowded_model = first_30(60)
    assert model.solves == crowded_model.solves == 2 and crowded_model.chain_loss <= sionna_adapter.CHAIN_LOSS
    assert np.isfinite(alone).all() and np.isfinite(crowded).all()
    np.testing.assert_allclose(crowded, alone, atol=0.05)


def test_two_walls_are_fitted_down_to_the_noise(rt):
    """Concrete 3x and marble 0.5x their scene values, 30 measurements with 0.3 dB of noise:
    the search (fine enough for the slabs' narrow basins), Levenberg–Marquardt and a restart
    find concrete within 5 % and fit the samples as well as the truth does (marble, a thin
    wall here, has equivalent basins: the data cannot choose its permittivity, only its
    effect); the held-out error falls to the noise; the scene is traced once."""
    truth = {"concrete": 3 * 5.24, "marble": 0.5 * 7.074}
    n, noise_db = 30, 0.3
    data = _measure(rt, {m: {"relative_permittivity": v} for m, v in truth.items()}, _receivers(n, seed=5),
                    noise_db=noise_db)
    settings = FitSettings(learn=("relative_permittivity",), materials=("concrete", "marble"), iterations=20,
                           holdout=0.25, noise_db=noise_db, search_sweeps=2, restarts=1)
    result = fit_materials(_street(rt), data, settings, RAYS)
    assert result.learned[("concrete", "relative_permittivity")] == pytest.approx(truth["concrete"], rel=0.05)
    noise = np.random.default_rng(1).normal(0.0, noise_db, n)  # what _measure added
    at_truth = float(np.sqrt(np.mean(noise[~result.holdout_mask] ** 2)))
    assert result.rmse_db["fit"]["after"] <= 1.2 * at_truth, (result.rmse_db, at_truth)
    assert result.rmse_db["held_out"]["after"] < 2 * noise_db < result.rmse_db["held_out"]["before"]
    assert result.cost["traces"] == 1 and result.cost["field_evaluations"] > 300
    assert "descent" in {r["phase"] for r in result.history}


def test_no_path_at_all_is_minus_infinity_not_a_crash(rt):
    """Free space traced without the line of sight has no path: every pair is -inf dBm (the
    emulator then reports nothing), where Dr.Jit's sum over the empty path axis would fail."""
    from caviar_plugins.rt.received_power import ReceivedPower

    model = ReceivedPower(rt.load_scene(), RAYS, seed=0)
    model.place(np.array([[0.0, 0.0, 1.5], [5.0, 0.0, 1.5]]), np.array([TX]))
    assert np.all(model.predict(np.array([[0, 0], [1, 0]]), 30.0) == -np.inf)


def test_a_fit_finds_a_known_permittivity_back_and_says_what_it_cannot_see(rt):
    """Concrete's ε_r is 3x the scene's (5.24 -> 15.7) in the "true" street; 16 measurements
    with 0.5 dB of noise, 4 held out. The fit learns concrete's permittivity within 10 % and
    the held-out error falls to the noise; the scattering coefficient, which no path of
    these rays (no diffuse reflection) depends on, is reported as not identifiable and
    left as it was."""
    truth = 3 * 5.24
    data = _measure(rt, {"concrete": {"relative_permittivity": truth}}, _receivers(16))
    settings = FitSettings(learn=("relative_permittivity", "scattering_coefficient"), materials=("concrete",),
                           iterations=12, search_points=40, search_sweeps=1, restarts=1, holdout=0.25,
                           noise_db=0.5)
    rows = []
    result = fit_materials(_street(rt), data, settings, RAYS, progress=rows.append)
    eps = result.learned[("concrete", "relative_permittivity")]
    assert eps == pytest.approx(truth, rel=0.10)
    assert ("concrete", "relative_permittivity") in result.identifiability.identifiable
    assert ("concrete", "scattering_coefficient") not in result.identifiability.identifiable
    assert result.identifiability.sensitivity_db[("concrete", "scattering_coefficient")] < 1e-3
    scattering = ("concrete", "scattering_coefficient")
    assert result.learned[scattering] == result.start[scattering]
    held = result.rmse_db["held_out"]
    assert held["after"] < 0.7 and held["before"] > 2 * held["after"], held
    assert result.samples == {"total": 16, "fit": 12, "held_out": 4, "without_path": 0}
    assert rows and {r["phase"] for r in rows} == {"search", "descent"}, "progress per evaluation"


def test_rival_minima_are_the_other_basins_that_fit_within_the_noise():
    """A profile with its best at 4 and another basin at 9 within the threshold (and one at 1
    beyond it): 9 is a rival, 1 is not, and the best's own basin (3-5) is not."""
    from caviar_plugins.twin.search import rival_minima

    values = np.arange(12.0)
    sse = np.array([9.0, 8.0, 9.0, 5.0, 1.0, 3.0, 7.0, 6.0, 4.0, 2.5, 6.0, 8.0])
    assert rival_minima(values, sse, threshold=2.0) == [9.0]
    assert rival_minima(values, sse, threshold=8.0) == [1.0, 9.0]
    assert rival_minima(values, sse, threshold=1.0) == []


class _TwoSlabs:
    """A fit's problem in closed form, for the search alone: each sample hears two slabs, each
    at its own angle of incidence, whose power reflection oscillates with the slab's electrical
    thickness √(ε_r − sin²θ) (period 0.43: a 10 cm wall at 3.5 GHz), in its own mix of the two."""

    unknowns = [("wall", "relative_permittivity"), ("floor", "relative_permittivity")]

    def __init__(self, truth, n=60, seed=3):
        rng = np.random.default_rng(seed)
        self.mix = rng.uniform(0.05, 1.0, (n, 2))
        self.sin2 = np.sin(rng.uniform(0.0, 1.4, (n, 2))) ** 2
        self.frozen = {}
        at_truth = np.array([to_log(u[1], v) for u, v in zip(self.unknowns, truth, strict=True)])
        self.data = dataclasses.make_dataclass("Data", ["power_dbm"])(self.power(at_truth))

    def reflection(self, eps, k):
        r = np.sqrt(eps - self.sin2[:, k])
        return ((r - 1) / (r + 1)) ** 2 * (2.0 + np.cos(2 * np.pi * r / 0.43))

    def power(self, x):
        e = [from_log("relative_permittivity", float(v)) for v in x]
        return 10 * np.log10(self.mix[:, 0] * self.reflection(e[0], 0) + self.mix[:, 1] * self.reflection(e[1], 1))

    def predict(self, x):
        return self.power(x)

    def values(self, x):
        return {u: from_log(u[1], float(v)) for u, v in zip(self.unknowns, x, strict=True)}

    def jacobian(self, x, step=0.01, every=False):
        cols = []
        for k in range(len(x)):
            up, down = x.copy(), x.copy()
            up[k] += step
            down[k] -= step
            cols.append((self.power(up) - self.power(down)) / (2 * step))
        return np.stack(cols, axis=1)


def test_a_descent_from_a_rival_finds_the_pair_that_a_coordinate_search_missed():
    """Two slabs that make up for each other: with the wall two basins of its oscillation off
    and the floor set to match, Levenberg–Marquardt stays there (a local minimum
    well above the noise); a descent from the wall's rival value (as a search profile would
    list it: within a grid step of the truth) with the floor swept again finds both truths
    and fits to 0.01 dB."""
    from caviar_plugins.twin.search import levenberg_marquardt, rival_descents

    truth = (15.7, 9.0)
    problem = _TwoSlabs(truth)
    mask, held = np.ones(60, dtype=bool), np.zeros(60, dtype=bool)
    free = np.ones(2, dtype=bool)
    settings = FitSettings(noise_db=0.3, search_points=160, iterations=40, rival_starts=2)
    wrong_basin = (np.sqrt(15.7) + 2 * 0.43) ** 2  # two periods of the wall's oscillation off
    x0 = np.array([to_log("relative_permittivity", wrong_basin), to_log("relative_permittivity", 9.0)])
    x0, _ = coarse_search(problem, x0, np.array([False, True]), mask, held, settings, [], None)
    stuck, _ = levenberg_marquardt(problem, x0, free, mask, held, settings, [], None)
    assert rmse(problem.predict(stuck), problem.data.power_dbm, mask) > 0.3
    assert problem.values(stuck)[problem.unknowns[0]] > 20.0, "stuck in the wrong basin"
    ambiguous = {problem.unknowns[0]: [15.7 * 1.02]}
    found = rival_descents(problem, stuck, free, mask, held, settings, [], None, ambiguous)
    values = problem.values(found)
    assert values[problem.unknowns[0]] == pytest.approx(truth[0], rel=0.01)
    assert values[problem.unknowns[1]] == pytest.approx(truth[1], rel=0.01)
    assert rmse(problem.predict(found), problem.data.power_dbm, mask) < 0.01
    none = rival_descents(problem, stuck, free, mask, held, dataclasses.replace(settings, rival_starts=0), [],
                          None, ambiguous)
    assert np.array_equal(none, stuck), "rival_starts = 0 leaves the fit where it was"


def test_search_grid_spans_the_physical_range():
    eps = search_grid("relative_permittivity", 30)
    assert eps[0] == pytest.approx(1.5) and eps[-1] == pytest.approx(80.0)
    assert np.allclose(np.diff(np.sqrt(eps)), np.diff(np.sqrt(eps))[0])
    with pytest.raises(ValueError, match="learn: 'colour' is not a material property"):
        FitSettings(learn=("colour",))


def test_the_calibrated_scene_loads_with_the_learned_materials(rt, tmp_path):
    from caviar_plugins.rt.materials import MaterialValues, scene_materials, write_scene_xml

    source = pathlib.Path(rt.scene.simple_street_canyon)
    learned = {"marble": MaterialValues(21.0, 0.02, 0.0, 0.1), "tower": MaterialValues(9.0, 0.5, 0.0, 0.2)}
    target = tmp_path / "out" / "scene.xml"
    names = write_scene_xml(source, target, learned, groups={"tower": ["building_1"]})
    assert names == {"marble": "fitted-marble", "tower": "fitted-tower"}
    scene = rt.load_scene(str(target), merge_shapes=False)
    values = scene_materials(scene)
    assert values["fitted-marble"].relative_permittivity == pytest.approx(21.0)
    assert values["fitted-tower"].conductivity == pytest.approx(0.5)
    glass = scene_materials(_street(rt))["glass"].relative_permittivity
    assert values["glass"].relative_permittivity == pytest.approx(glass), "the others untouched"
    assert scene.objects["building_1"].radio_material.name == "fitted-tower"
    assert len(scene.objects) == 7, "every mesh found from the new folder"


# -- the command line -----------------------------------------------------------------------

def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "caviar_plugins.tools.fit_scene", *args], capture_output=True,
                          text=True, timeout=600, cwd=cwd)


@pytest.mark.parametrize("extra, named", [
    (["--holdout", "1.5"], "--holdout: expected a share in [0, 1)"),
    (["--learn", "colour"], "--learn: 'colour' is not a material property"),
    (["--samples", "0"], "--samples: expected a whole number from 1"),
    (["--max-depth", "-1"], "--max-depth: expected a whole number from 0"),
    (["--seed", "-1"], "--seed: expected a whole number from 0"),
    (["--noise-db", "nan"], "--noise-db: expected a finite number"),
    (["--group", "tower"], "--group: expected NAME=GLOB"),
    (["--iterations", "0"], "--iterations: expected a whole number from 1"),
])
def test_bad_flags_are_named_before_any_work(tmp_path, extra, named):
    m = from_rows([("r", _row())], "t").write_csv(tmp_path / "m.csv")
    r = _cli("central_park", str(m), "--out", str(tmp_path / "o"), *extra)
    assert r.returncode == 2 and named in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_bad_files_are_named(tmp_path):
    m = from_rows([("r", _row())], "t").write_csv(tmp_path / "m.csv")
    (tmp_path / "file").write_text("")
    bad = tmp_path / "bad.csv"
    bad.write_text(",".join(FIELDS) + "\n" + ",".join(["1"] * (len(FIELDS) - 1) + ["x"]) + "\n")
    for args, named in (
        (["no_such_scene", str(m), "--out", str(tmp_path / "o")], "SCENE: scene 'no_such_scene'"),
        (["central_park", str(tmp_path / "none.csv"), "--out", str(tmp_path / "o")], "none.csv: no such file"),
        (["central_park", str(bad), "--out", str(tmp_path / "o")], "row 1 (line 2): field 'bandwidth_hz'"),
        (["central_park", str(m), "--out", str(tmp_path / "file")], "--out:"),
    ):
        r = _cli(*args)
        assert r.returncode == 2 and named in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)


def test_fit_scene_writes_the_scene_the_report_and_the_figure(rt, tmp_path):
    data = _measure(rt, {"marble": {"relative_permittivity": 3 * 7.074}}, _receivers(12))
    data.pdp = [(np.array([0.0, 5e-8]), np.array([-70.0, -80.0 - i])) for i in range(12)]  # (the CLI's path for them)
    m = data.write_csv(tmp_path / "m.csv")
    r = _cli(str(rt.scene.simple_street_canyon), str(m), "--out", str(tmp_path / "fit"), "--materials", "marble",
             "--learn", "relative_permittivity", "--iterations", "3", "--search-points", "8", "--samples", "20000",
             "--max-depth", "2", "--threads", "1", "--holdout", "0.25", "--restarts", "1")
    assert r.returncode == 0, r.stderr
    assert "iteration 0: fit" in r.stderr and "held-out RMSE" in r.stderr
    report = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert report["rmse_db"]["fit"]["after"] <= report["rmse_db"]["fit"]["before"] + 1e-9
    assert report["samples"]["held_out"] == 3
    scene = rt.load_scene(str(tmp_path / "fit" / "scene.xml"))
    learned = report["learned"]["marble.relative_permittivity"]["learned"]
    assert report["names_in_scene_xml"] == {"marble": "fitted-marble"}
    assert float(scene.radio_materials["fitted-marble"].relative_permittivity[0]) == pytest.approx(learned, rel=1e-6)
    assert (tmp_path / "fit" / "fit.png").stat().st_size > 10_000
    assert "RMS delay spread of 12 profiles" in r.stderr and report["delay_spread_ns"]["samples"] == 12
