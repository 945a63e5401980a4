"""The uplink (issue #41, part 2): PUSCH open-loop power control by hand, and the uplink
SINR through the radio-network plugin against a hand link budget."""

from __future__ import annotations

import math

import numpy as np
import pytest

import caviar
from caviar_plugins.network.uplink import UplinkSettings, noise_per_prb_mw, tx_power_dbm
from network_configs import (
    OTHER,
    VICTIM,
    eager_and_compiled,
    last_reports,
    reported,
    run_network,
    two_sites,
    ue_reports,
)

LAMBDA = 299_792_458.0 / 3.5e9


@pytest.mark.parametrize("alpha", [1.0, 0.8, 0.4])
def test_power_control_is_p0_plus_alpha_pathloss_within_the_ues_limit(alpha):
    s = UplinkSettings(p0_dbm=-90.0, alpha=alpha, ue_max_power_dbm=23.0)
    pl = np.array([70.0, 90.0, 110.0, 130.0, 150.0, 250.0])
    prb = 51
    got = tx_power_dbm(s, pl, prb)
    hand = np.minimum(-90.0 + alpha * pl + 10 * math.log10(prb), 23.0)
    np.testing.assert_allclose(got, hand, atol=1e-4)  # (Sionna computes in float32)
    below = hand < 23.0
    assert below.any() and (~below).any()  # both regimes covered
    # The cell receives P0 + (α − 1)·PL per PRB while the UE has power to spare.
    received = got - 10 * math.log10(prb) - pl
    np.testing.assert_allclose(received[below], -90.0 + (alpha - 1) * pl[below], atol=1e-4)


def _gain(site, azimuth, ue):
    """Friis × the TR 38.901 element on the horizon (linear), from a site toward a UE."""
    d = np.asarray(ue) - np.asarray(site)
    phi = (math.degrees(math.atan2(d[1], d[0])) - azimuth + 180) % 360 - 180
    element_db = 8.0 - min(12 * (phi / 65) ** 2, 30.0)
    return (LAMBDA / (4 * math.pi * np.linalg.norm(d))) ** 2 * 10 ** (element_db / 10)


def test_the_uplink_sinr_is_the_hand_budget_with_the_other_cells_ue_interfering(tmp_path):
    log = run_network(tmp_path, two_sites(uplink={"p0_dbm": -90.0, "alpha": 1.0, "ue_max_power_dbm": 23.0}))
    last = last_reports(log)
    assert last["victim"]["serving_cell"] == "A/0" and last["other"]["serving_cell"] == "B/0"
    a, b = ((0.0, 0.0, 25.0), 0.0), ((400.0, 0.0, 25.0), 180.0)  # (network_configs.SITE_A, SITE_B)
    victim, other = VICTIM, OTHER
    array = 10 * math.log10(8)
    # Each UE's pathloss from its cell's RSRP (array included); α = 1: full compensation.
    pl_victim = -(10 * math.log10(_gain(*a, victim)) + array)
    pl_other = -(10 * math.log10(_gain(*b, other)) + array)
    assert last["victim"]["ul_tx_power_dbm"] == pytest.approx(-90 + pl_victim + 10 * math.log10(51), abs=0.01)
    assert last["other"]["ul_tx_power_dbm"] == pytest.approx(-90 + pl_other + 10 * math.log10(51), abs=0.01)
    # At A: P0 per PRB from the victim; the other UE (scheduled by B in every slot) through
    # A's element pattern (A's array serves the victim), over kT·B_PRB·NF.
    interference = 10 ** ((-90 + pl_other) / 10) * _gain(*a, other)
    noise = noise_per_prb_mw(30e3, 5.0)
    hand = 10 * math.log10(10 ** (-90 / 10) / (noise + interference))
    assert last["victim"]["ul_sinr_db"] == pytest.approx(hand, abs=0.05)
    assert last["victim"]["ul_throughput_mbps"] > 0 and 0 <= last["victim"]["ul_mcs"] <= 28
    # caviar-core report adds the uplink's CDFs and percentiles.
    import json

    rep = reported(tmp_path)
    assert (rep / "network-cdf.png").stat().st_size > 20_000
    ul = json.loads((rep / "network.json").read_text())["ue_types"]["car"]["ul_sinr_db"]
    sinrs = [u["ul_sinr_db"] for u in ue_reports(log)]
    assert ul["p50"] == pytest.approx(float(np.percentile(sinrs, 50)), abs=1e-3)


def test_power_control_out_of_range_is_refused_before_the_run_naming_the_key(tmp_path):
    cfg = tmp_path / "net.toml"
    for bad, key, what in (({"alpha": 0.75}, "alpha", "expected one of 0, 0.4"),
                           ({"p0_dbm": 30.0}, "p0_dbm", "expected -202..24 dBm")):
        cfg.write_text(two_sites(uplink=bad))
        with pytest.raises(caviar.ConfigError) as e:
            caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
        assert "net.toml:" in str(e.value) and f"uplink.{key}" in str(e.value) and what in str(e.value), e.value
    assert not (tmp_path / "run").exists()


def test_with_ssb_beams_the_ue_estimates_its_pathloss_from_the_best_beams_rsrp(tmp_path):
    log = run_network(tmp_path, two_sites(beams={"horizontal": 8}, uplink={"p0_dbm": -90.0, "alpha": 1.0}))
    for ue in ("victim", "other"):
        last = last_reports(log)[ue]
        rx = last["rsrp_dbm"][last["serving_cell"]] + 10 * math.log10(12 * 51)  # the best beam's, whole band
        pathloss = 46.0 - rx
        assert last["ul_tx_power_dbm"] == pytest.approx(-90 + pathloss + 10 * math.log10(51), abs=0.02)
        assert math.isfinite(last["ul_sinr_db"]) and last["ul_throughput_mbps"] > 0


def test_the_compiled_uplink_gives_the_eager_powers_and_sinrs_in_fewer_torch_operations():
    """``compile``: the uplink's powers and per-slot SINRs as one ``torch.compile`` program give
    the eager numbers (to float32's rounding: Sionna's power control computes in it), at a
    first UE count and at others (a dynamic size after the first change: no compile a count),
    with less than half of eager's torch operations (each a kernel launch on a GPU) outside it."""
    import torch

    from caviar_plugins.network.cells import Cell
    from caviar_plugins.network.uplink import uplink

    cells = [Cell(name=f"c{k}", site=f"s{k}", index=k, position=(100.0 * k, 0.0, 25.0), azimuth_deg=60.0 * k,
                  downtilt_deg=4.0, tx_power_dbm=43.0, carrier_hz=3.5e9 if k < 3 else 2.1e9, bandwidth_hz=20e6,
                  array=(2, 4)) for k in range(4)]
    s = UplinkSettings(p0_dbm=-90.0, alpha=0.8, ue_max_power_dbm=23.0)
    rng = np.random.default_rng(3)
    for n_ue in (7, 11, 9):
        gains = torch.as_tensor(rng.exponential(1e-10, (n_ue, 4, 2, 3)) * 10 ** rng.uniform(-4, 0, (n_ue, 1, 1, 1)))
        serving = rng.integers(-1, 4, n_ue)
        serving[:4] = [0, 1, -1, 3]  # (one UE without a cell)
        args = (cells, s, serving, np.zeros((n_ue, 4, 2)), gains, rng.integers(0, 3, (n_ue, 4)), 51, 30e3, 16, "cpu",
                rng.random(n_ue) < 0.8)
        out = eager_and_compiled(uplink, args, compiles=n_ue != 9)  # (7 UEs compile, 11 once more: dynamic)
        (tx, sinr, eager_ops), (tx_c, sinr_c, compiled_ops) = out[False], out[True]
        assert np.isfinite(tx).all() and (tx <= 23.0 + 1e-6).all() and (tx < 23.0).any()
        np.testing.assert_allclose(tx_c, tx, rtol=1e-6)  # (Sionna's power control: float32)
        assert np.array_equal(np.isnan(sinr_c), np.isnan(sinr)) and np.isnan(sinr[:, 2]).all()
        np.testing.assert_allclose(sinr_c, sinr, rtol=1e-6)
        # (outside the program: the inputs made tensors, the pathloss, the dB)
        assert compiled_ops <= 45 < 90 <= eager_ops, (compiled_ops, eager_ops)


def _sinrs_apart(cells, serving, talking, dl: dict, ul: tuple, compiled: bool) -> tuple:
    """The downlink's and the uplink's SINRs, each by its own function (two programs compiled)."""
    from caviar_plugins.network.downlink import downlink_sinr
    from caviar_plugins.network.uplink import mean_sinr_db, uplink

    dl_slot, sinr, sir = downlink_sinr(cells, None, None, serving, talking, **dl, compiled=compiled)
    tx, ul_slot = uplink(*ul, linear=True, compiled=compiled)
    return dl_slot, sinr, sir, tx, ul_slot, mean_sinr_db(ul_slot)


def _sinrs_joint(cells, serving, talking, dl: dict, ul: tuple, compiled: bool) -> tuple:
    """The same as one program (``sinrs.both_directions``)."""
    from caviar_plugins.network.downlink import beamformed_args
    from caviar_plugins.network.sinrs import both_directions
    from caviar_plugins.network.uplink import uplink_args

    return both_directions(beamformed_args(cells, serving, talking, **dl), uplink_args(*ul), compiled)


def test_both_directions_as_one_program_give_the_two_programs_numbers_in_one_compiled_call():
    """With beams and the uplink the step's SINRs of both directions are one program
    (``sinrs.both_directions``, which ``sinrs.step_sinrs`` chooses for the plugin): eager, the
    very numbers of the downlink's and the uplink's own functions; compiled, the same to float32's
    rounding (the power control's) in one compiled call where the two apart make two, at UE
    counts that change (a dynamic size)."""
    import types

    import torch
    from torch.profiler import ProfilerActivity, profile

    from caviar_plugins.network.cells import Cell
    from caviar_plugins.network.sinrs import step_sinrs

    cells = [Cell(name=f"c{k}", site=f"s{k}", index=k, position=(100.0 * k, 0.0, 25.0), azimuth_deg=60.0 * k,
                  downtilt_deg=4.0, tx_power_dbm=43.0, carrier_hz=3.5e9 if k < 3 else 2.1e9, bandwidth_hz=20e6,
                  array=(2, 4)) for k in range(4)]
    s = UplinkSettings(p0_dbm=-90.0, alpha=0.8, ue_max_power_dbm=23.0)
    rng = np.random.default_rng(5)

    def regions(function, args) -> int:
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            function(*args, compiled=True)
        return sum(1 for e in prof.events() if e.name.startswith("Torch-Compiled Region"))

    for n_ue in (6, 10):
        gains = torch.as_tensor(rng.exponential(1e-10, (n_ue, 4, 2, 3)) * 10 ** rng.uniform(-4, 0, (n_ue, 1, 1, 1)))
        serving, best = rng.integers(-1, 4, n_ue), rng.integers(0, 3, (n_ue, 4))
        serving[:3] = [0, -1, 3]  # (a UE without a cell)
        talking, ul_talking = rng.random(n_ue) < 0.8, rng.random(n_ue) < 0.7
        dl = dict(noise_figure_db=7.0, scheduled=True, beams=(gains, best), slots=16, subband_prbs=np.array([26, 25]),
                  device="cpu", linear=True)
        args = (cells, serving, talking, dl, (cells, s, serving, np.zeros((n_ue, 4, 2)), gains, best, 51, 30e3, 16,
                                              "cpu", ul_talking))
        two = _sinrs_apart(*args, compiled=False)
        assert np.isnan(two[1][1]) and np.isfinite(two[3]).all() and np.isfinite(two[5][serving >= 0]).all()
        for got, want in zip(_sinrs_joint(*args, compiled=False), two, strict=True):  # (eager: the same numbers)
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        # (the plugin's choice, step_sinrs: each direction's UEs with data where they belong; no uplink: None)
        p = types.SimpleNamespace(noise_figure_db=7.0, interference="scheduled", uplink=s, num_prb=51,
                                  subcarrier_spacing_hz=30e3, compile=False)
        *down, up = step_sinrs(p, cells, None, None, serving, talking, ul_talking, (gains, best), 16,
                               np.array([26, 25]), "cpu")
        for got, want in zip([*down, *up], two, strict=True):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        alone = step_sinrs(types.SimpleNamespace(**{**vars(p), "uplink": None}), cells, None, None, serving, talking,
                           None, (gains, best), 16, np.array([26, 25]), "cpu")
        assert alone[3] is None and all(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
                                        for a, b in zip(alone[:3], two[:3], strict=True))
        _sinrs_apart(*args, compiled=True)  # (compiles, or at a new count recompiles: a dynamic size)
        _sinrs_joint(*args, compiled=True)
        assert regions(_sinrs_apart, args) == 2 and regions(_sinrs_joint, args) == 1
        for got, want in zip(_sinrs_joint(*args, compiled=True), two, strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6)
