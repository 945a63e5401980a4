"""SSB beams from the channel (issue #41, part 1): the DFT codebook's gains and the SINR
with the interferer's scheduled beam, against the array factor computed by hand."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from caviar_plugins.network.beams import Codebook, beam_gains, beamformed_sinr_db, line_of_sight
from network_configs import (
    OTHER,
    SITE_B,
    VICTIM,
    eager_and_compiled,
    last_reports,
    ray_traced,
    reported,
    run_network,
    sector,
    two_sites,
    ue_reports,
)

CARRIER, N = 3.5e9, 8
LAMBDA = 299_792_458.0 / CARRIER
NOISE_MW = 10 ** ((-174 + 10 * math.log10(20e6) + 7) / 10)
# the two cells facing each other of network_configs.two_sites, 46 dBm, a 1×N array
A = sector("A", 0, (0.0, 0.0, 25.0), 0.0, array=(1, N))
B = sector("B", 1, (400.0, 0.0, 25.0), 180.0, array=(1, N))


def _dirichlet(u, u_beam):
    """|Σ_n exp(jπn(u − u_b))|² / N for an N-element half-wavelength line: the array factor."""
    x = math.pi * (u - u_beam) / 2
    return N if abs(math.sin(x)) < 1e-12 else math.sin(N * x) ** 2 / (N * math.sin(x) ** 2)


def _element_db(phi_deg):  # TR 38.901 Table 7.3-1 on the horizon, no tilt
    return 8.0 - min(12 * (phi_deg / 65) ** 2, 30.0)


def _hand(cell, ue, beam_u):
    """Friis × element × array factor of `cell`'s beam steered to `beam_u`, toward `ue` (same height)."""
    d = np.asarray(ue) - np.asarray(cell.position)
    dist = float(np.linalg.norm(d))
    phi = math.degrees(math.atan2(d[1], d[0])) - cell.azimuth_deg
    phi = (phi + 180) % 360 - 180
    u = math.sin(math.radians(phi))
    return (LAMBDA / (4 * math.pi * dist)) ** 2 * 10 ** (_element_db(phi) / 10) * _dirichlet(u, beam_u), u


def _best(u):  # the DFT beam nearest to u: the codebook's best for a single path
    grid = (2 * np.arange(N) + 1) / N - 1
    return float(grid[np.argmin(np.abs(grid - u))])


def _victim_by_hand(victim, other):
    """The victim's SINR by hand: A's best beam toward it, B's best beam toward ``other``
    leaking onto it. (SINR dB, the signal's and the leak's linear gains, u toward the victim)."""
    _, u_a = _hand(A, victim, 0.0)
    signal, _ = _hand(A, victim, _best(u_a))
    _, u_b = _hand(B, other, 0.0)
    leak, _ = _hand(B, victim, _best(u_b))
    power = 10 ** (46 / 10)
    return 10 * math.log10(power * signal / (NOISE_MW + power * leak)), signal, leak, u_a


@pytest.mark.parametrize("toward_victim", [True, False])
def test_two_cells_sinr_is_the_hand_array_factor_with_the_interferers_beam_on_or_off_the_victim(toward_victim):
    victim = np.array(VICTIM)  # served by A
    # B's own UE: on the line from B through the victim (B's beam then points at it), or off to B's other side.
    other = B.position + 0.5 * (victim - B.position) if toward_victim else np.array(OTHER)
    cells, ues = [A, B], np.array([victim, other])
    codebook = Codebook(rows=1, cols=N, beams_h=N)
    amplitude, departure = line_of_sight(cells, ues)
    gains = np.stack([beam_gains(c, codebook, amplitude[:, k], departure[:, k]) for k, c in enumerate(cells)], 1)
    beam = gains[np.arange(2), [0, 1]].argmax(-1)  # each UE's best beam from its serving cell
    sinr = beamformed_sinr_db(cells, gains, np.array([0, 1]), beam, scheduled_beam=beam, noise_mw=NOISE_MW)[0]

    # By hand: A's best beam toward the victim, B's best beam toward its own UE, on the victim.
    hand, _, leak, _ = _victim_by_hand(victim, other)
    print(f"toward the victim: {toward_victim}: SINR {sinr:.3f} dB, by hand {hand:.3f} dB")
    assert sinr == pytest.approx(hand, abs=0.1)
    if toward_victim:
        assert leak > 0.5 * N * (LAMBDA / (4 * math.pi * np.linalg.norm(victim - B.position))) ** 2  # near the peak
    else:
        assert hand > 10  # the interferer's beam points away


def test_the_beams_tile_the_panel_and_a_beam_on_a_path_gains_the_array():
    cell = sector("A", 0, (0.0, 0.0, 0.0), 30.0)
    codebook = Codebook(rows=4, cols=8, beams_h=8, beams_v=4)
    w = codebook.weights()
    assert w.shape == (32, 32) and np.allclose(w @ w.conj().T, np.eye(32), atol=1e-12)  # orthonormal DFT beams
    # A unit path along each beam's own direction gains rows·cols = 32 on that beam, ~0 on the
    # others (the four corner beams, u² + v² > 1, point at no real direction).
    u, v = codebook.pointing().T
    real = u**2 + v**2 < 1
    assert real.sum() == 28
    a_rad = math.radians(30.0)
    # the panel frame's (x', y', z') for spatial frequencies (u, v): x' = sqrt(1 - u² - v²)
    x = np.sqrt(np.clip(1 - u**2 - v**2, 0, None))
    k = np.stack([math.cos(a_rad) * x - math.sin(a_rad) * u, math.sin(a_rad) * x + math.cos(a_rad) * u, v], -1)
    g = beam_gains(cell, codebook, np.ones((28, 1)), k[real][:, None, :])
    on = g[np.arange(28), np.flatnonzero(real)]
    assert np.allclose(on, 32) and np.allclose(g.sum(axis=1), 32)  # all of it on its own beam


def test_a_codebook_larger_than_the_array_is_refused_naming_the_key():
    with pytest.raises(ValueError, match=r"beams: 16 horizontal beams on 8 columns; expected 1\.\.8"):
        Codebook(rows=4, cols=8, beams_h=16)
    with pytest.raises(ValueError, match=r"beams: 5 vertical beams on 4 rows"):
        Codebook(rows=4, cols=8, beams_h=8, beams_v=5)


def test_the_ray_traced_paths_give_the_free_space_beams_in_an_empty_scene():
    """A ray test: with only the direct path, each sector's beam gains from the traced
    departure directions are those of the straight line, beam by beam."""
    from caviar_plugins.network.raytraced import NETWORK_RAYS, SiteTracer

    cells = [sector(f"A/{k}", k, (0.0, 0.0, 30.0), az, site="A", downtilt_deg=6.0, array=(4, 8))
             for k, az in enumerate((0.0, 120.0, 240.0))]
    ues = np.array([[120.0, 40.0, 1.5], [-80.0, -60.0, 1.5], [60.0, 150.0, 40.0]])
    traced = SiteTracer("empty", dataclasses.replace(NETWORK_RAYS, max_depth=0, samples_per_src=1000), cells).trace(ues)
    amplitude, departure = line_of_sight(cells, ues)
    codebook = Codebook(rows=4, cols=8, beams_h=8, beams_v=2)
    for k, cell in enumerate(cells):
        ray = beam_gains(cell, codebook, traced.amplitude[:, k], traced.departure[:, k])
        straight = beam_gains(cell, codebook, amplitude[:, k], departure[:, k])
        strong = straight > 1e-3 * straight.max(axis=1, keepdims=True)  # away from the nulls
        np.testing.assert_allclose(10 * np.log10(ray[strong]), 10 * np.log10(straight[strong]), atol=0.02)
        assert (ray.argmax(axis=1) == straight.argmax(axis=1)).all()


def _beams(other=OTHER, beams: int = N, **more) -> str:
    """A and B (network_configs.two_sites) with ``beams`` horizontal SSB beams, 7 dB noise
    figure and A3 with 3 dB hysteresis; ``more``: two_sites' steps, other params."""
    return two_sites(other, noise_figure_db=7.0, beams={"horizontal": beams},
                     handover={"offset_db": 0.0, "hysteresis_db": 3.0}, **more)


@pytest.mark.parametrize("toward_victim", [True, False])
def test_in_the_network_the_victims_sinr_is_the_hand_array_factor(tmp_path, toward_victim):
    """The radio-network plugin with beams: the same two cells and two UEs, through cell
    selection on L1-RSRP, the serving beam and the interferer's scheduled beam."""
    victim = np.array(VICTIM)
    b = np.array(SITE_B["position"])
    other = b + 0.5 * (victim - b) if toward_victim else np.array(OTHER)
    log = run_network(tmp_path, _beams(other))
    last = last_reports(log)
    assert last["victim"]["serving_cell"] == "A/0" and last["other"]["serving_cell"] == "B/0"
    hand, signal, _, u_a = _victim_by_hand(victim, other)
    power = 10 ** (46 / 10)
    assert last["victim"]["sinr_db"] == pytest.approx(hand, abs=0.1)
    # L1-RSRP: the best beam's received power per resource element.
    rsrp = 10 * math.log10(power * signal) - 10 * math.log10(12 * 51)
    assert last["victim"]["rsrp_dbm"]["A/0"] == pytest.approx(rsrp, abs=0.01)
    # The serving beam, reported where it points: the DFT direction nearest the victim's.
    assert last["victim"]["beam_azimuth_deg"] == pytest.approx(math.degrees(math.asin(_best(u_a))), abs=0.01)
    assert abs(math.degrees(math.asin(_best(u_a))) - math.degrees(math.atan2(60, 180))) < 8  # half a beam
    if not toward_victim:
        return
    # caviar-core report draws the serving beams on the map.
    assert (reported(tmp_path) / "network-handovers.png").stat().st_size > 10_000


def test_a_codebook_larger_than_the_panel_is_refused_before_the_run_naming_the_key(tmp_path):
    import caviar

    cfg = tmp_path / "net.toml"
    cfg.write_text(_beams(beams=16))
    with pytest.raises(caviar.ConfigError, match=r"net\.toml:\d+: modules\.net\.params\.beams: 16 horizontal beams "
                                                 r"on 8 columns"):
        caviar.Simulation.from_toml(cfg, out=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_in_an_empty_scene_the_ray_traced_beams_give_the_free_space_sinr(tmp_path):
    """A ray test through the plugin: the traced paths' departure directions and phases,
    moved with the UEs per subband, give the straight line's beams."""
    sinr = {}
    for channel in ("free-space", "ray-traced"):
        traced = ray_traced(max_depth=0, samples_per_src=1000) if channel == "ray-traced" else {}
        log = run_network(tmp_path, _beams(**traced), channel, f"{channel}.toml")
        sinr[channel] = {u["UE_Id"]: u["sinr_db"] for u in ue_reports(log)}
    assert sinr["ray-traced"] == pytest.approx(sinr["free-space"], abs=0.05)


def test_the_kept_beam_responses_give_each_cells_beam_gains_per_frequency():
    """``gains_of_responses`` on ``beam_responses`` (the responses kept from one trace to the
    next, one batched product a step) equals :func:`beam_gains` (the channel across the
    panel, then the beams), cell by cell and frequency by frequency, with codebooks of
    different sizes (the smaller one's missing beams: 0)."""
    from caviar_plugins.network.beams import beam_responses, gains_of_responses

    rng = np.random.default_rng(12)
    cells = [sector("a", 0, (0.0, 0.0, 25.0), 0.0, array=(1, N)),
             sector("b", 1, (300.0, 0.0, 25.0), 120.0, array=(1, N))]
    codebooks = [Codebook(1, N, N), Codebook(1, N, 4)]
    n_ue, n_path, n_f = 5, 6, 3
    departure = rng.normal(size=(n_ue, 2, n_path, 3))
    departure /= np.linalg.norm(departure, axis=-1, keepdims=True)
    amplitude = (rng.normal(size=(n_ue, 2, n_path, n_f)) + 1j * rng.normal(size=(n_ue, 2, n_path, n_f))) * 1e-6
    amplitude[0, 1, 3:] = 0.0  # (fewer paths: zeros)
    kept = gains_of_responses(amplitude, beam_responses(cells, codebooks, departure))
    assert kept.shape == (n_ue, 2, n_f, N)
    for c, (cell, cb) in enumerate(zip(cells, codebooks, strict=True)):
        for f in range(n_f):
            np.testing.assert_allclose(kept[:, c, f, :cb.size], beam_gains(cell, cb, amplitude[:, c, :, f],
                                                                           departure[:, c]), rtol=1e-10)
        assert not kept[:, c, :, cb.size:].any()


def test_the_plugin_computes_the_beam_responses_once_per_trace(tmp_path, monkeypatch):
    """The paths' beam responses change only with a trace: over 6 steps with a trace every
    3, the plugin computes them twice, however often the gains are evaluated."""
    from caviar_plugins.network import traced_channel
    from caviar_plugins.network.raytraced import SiteTracer

    calls = {"responses": 0, "traces": 0}
    responses, trace = traced_channel.beam_responses, SiteTracer.trace

    def counted_responses(*args, **kwargs):
        calls["responses"] += 1
        return responses(*args, **kwargs)

    def counted_trace(self, *args, **kwargs):
        calls["traces"] += 1
        return trace(self, *args, **kwargs)

    monkeypatch.setattr(traced_channel, "beam_responses", counted_responses)
    monkeypatch.setattr(SiteTracer, "trace", counted_trace)
    log = run_network(tmp_path, _beams(steps=6, **ray_traced(max_depth=0, samples_per_src=1000, refresh_s=0.03)),
                      name="traced.toml")
    assert len(ue_reports(log)) == 6 * 2  # every step measured both UEs
    assert calls == {"responses": 2, "traces": 2}


def test_the_slots_schedule_is_each_cells_ues_in_turn_and_a_repeated_call_gets_its_own_copy():
    """``scheduled_ues``: each cell's UEs in UE order, one a slot, round again (-1 for a cell that
    serves nobody), by a loop here; the same arguments again (a step's downlink and uplink) give
    the same numbers in an array of their own (writing one leaves the next call's alone), other
    arguments their own."""
    from caviar_plugins.network.beams import scheduled_ues

    rng = np.random.default_rng(8)
    serving = rng.integers(-1, 4, 30)  # (cell 4 of 5: nobody)
    want = np.full((11, 5), -1)
    for c in range(5):
        mine = [u for u in range(30) if serving[u] == c]
        for slot in range(11):
            if mine:
                want[slot, c] = mine[slot % len(mine)]
    first = scheduled_ues(serving, 5, 11)
    np.testing.assert_array_equal(first, want)
    first[:] = 99
    np.testing.assert_array_equal(scheduled_ues(serving.copy(), 5, 11), want)
    other = np.where(serving == 0, -1, serving)
    assert (scheduled_ues(other, 5, 11)[:, 0] == -1).all()
    np.testing.assert_array_equal(scheduled_ues(serving, 5, 12)[:11], want)


@pytest.mark.parametrize("silent_idle", [True, False])
def test_the_compiled_downlink_gives_the_eager_sinrs_in_fewer_torch_operations(silent_idle):
    """``compile``: the downlink's per-slot SINRs and its wideband SINR and SIR as one
    ``torch.compile`` program give the eager numbers to float64's rounding (cells serving nobody
    silent or sending over their codebook), at a first UE count and at others (a dynamic size
    after the first change: no compile a count), with fewer torch operations outside it."""
    import torch

    from caviar_plugins.network.beams import slot_beams, slot_sinr_and_wideband
    from caviar_plugins.network.cells import Cell

    cells = [Cell(name=f"c{k}", site=f"s{k}", index=k, position=(100.0 * k, 0.0, 25.0), azimuth_deg=60.0 * k,
                  downtilt_deg=4.0, tx_power_dbm=40.0 + k, carrier_hz=3.5e9 if k < 3 else 2.1e9, bandwidth_hz=20e6,
                  array=(2, 4)) for k in range(4)]
    rng = np.random.default_rng(4)
    for n_ue in (7, 11, 9):
        gains = torch.as_tensor(rng.exponential(1e-10, (n_ue, 4, 2, 3)))
        serving = rng.integers(-1, 2, n_ue)  # (cells 2 and 3 serve nobody)
        serving[:2] = [0, -1]
        best = rng.integers(0, 3, n_ue)
        args = (cells, gains, serving, best, slot_beams(serving, best, 4, 16), rng.uniform(1e-13, 1e-12, n_ue),
                silent_idle, np.array([2.0, 1.0]), "cpu")
        out = eager_and_compiled(slot_sinr_and_wideband, args, compiles=n_ue != 9)  # (7 UEs compile, 11 once more)
        (per_slot, sinr, sir, eager_ops), (per_slot_c, sinr_c, sir_c, compiled_ops) = out[False], out[True]
        assert np.isnan(per_slot[:, 1]).all() and np.isnan(sinr[1]) and np.isfinite(sinr[0])
        np.testing.assert_allclose(per_slot_c, per_slot, rtol=1e-12)  # (NaN where NaN)
        np.testing.assert_allclose(sinr_c, sinr, rtol=1e-12)
        np.testing.assert_allclose(sir_c, sir, rtol=1e-12)
        assert compiled_ops < eager_ops - 10, (compiled_ops, eager_ops)
