"""`caviar-core export deepmimo`: a ray-traced run with sionna-link's publish_paths, exported
and loaded with the real deepmimo package (4.x), whose channels and path tables are checked
against what the run recorded; the published paths checked against Sionna's own MIMO channel;
bad input checked for its messages."""

import json
import pathlib

import deepmimo
import numpy as np
import pytest

import caviar
from caviar_plugins.radio import RadioConfig, RadioScene
from caviar_plugins.radio.path_data import PathData
from caviar_plugins.rt.settings import with_raytracing
from configs import CENTRAL_PARK, episode, sionna_link, waypoint_uav
from conftest import write_config

FC = 40e9
SPEED_OF_LIGHT = 299_792_458.0
RECORDED_AT_HZ = 0.0
"""The baseband frequency at which sionna-link's recorded H is Sionna's CFR: 0, the
narrowband channel at the carrier, Σ a·exp(−j2π f_c τ) (scene.py calls
``paths.cfr(frequencies=[0.0])``; ``cfr`` adds exp(−j2π f τ) on top of the carrier phase
``cir`` applied)."""
DEEPMIMO_CODE = {1: 1, 2: 3, 4: 4, 8: 2}  # Sionna's interaction type -> DeepMIMO's digit

def config(second: str | pathlib.Path = CENTRAL_PARK, steps: int = 3, publish_paths: bool = True) -> str:
    """uav1 over Central Park at 10 m/s and uav2 along ``second`` at 6 m/s, ``steps`` steps of 1 s, under
    a sionna-link of single antennas publishing its paths (``publish_paths``)."""
    return (episode(1.0, ["mobility", "communications"], steps=steps, seed=7)
            + waypoint_uav(CENTRAL_PARK, 10.0, name="uav1", ue_id="uav1")
            + waypoint_uav(second, 6.0, name="uav2", ue_id="uav2")
            + sionna_link(20000, raytracing={"max_depth": 3}, params_table=True, uav_mesh=False, tx_array=[1, 1],
                          rx_array=[1, 1], publish_paths=publish_paths))


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A 3-step run of two UAVs over Central Park (single antennas, TR 38.901 patterns),
    exported with the command; the run's log, its per-step paths and the scenario folder."""
    tmp = tmp_path_factory.mktemp("deepmimo")
    second = tmp / "second.csv"
    second.write_text("X,Y,Z\n-153.66,128.93,9.23\n-134.66,118.48,9.23\n-100.0,150.0,20.0\n")
    cfg = write_config(tmp, config(second))
    log = caviar.Simulation.from_toml(cfg, out=tmp / "run").run()
    from caviar_plugins.tools.export.cli import main

    assert main(["deepmimo", str(tmp / "run"), str(tmp / "scen"), "--quiet"]) == 0
    paths: dict[int, dict[str, PathData]] = {}
    for m in log.decoded("communications.paths.*"):
        paths.setdefault(m.step, {})[m.topic.rsplit(".", 1)[1]] = PathData.from_bytes(m.data)
    return log, paths, tmp / "scen"


def load(folder):
    deepmimo.config.set("scenarios_folder", str(folder.parent))
    return deepmimo.load(folder.name, max_paths=25)


def test_the_run_publishes_every_ues_paths_each_step(exported):
    log, paths, _ = exported
    assert sorted(paths) == [0, 1, 2] and all(sorted(p) == ["uav1", "uav2"] for p in paths.values())
    links = log.topic("communications.link")
    for row in links.iter_rows(named=True):
        p = paths[row["step"]][row["UE_Id"]]
        assert p.n_paths == row["n_paths"] > 0
        assert p.frequency_hz == FC and p.settings["scene"] == "central_park" and p.settings["module"] == "comm"
        np.testing.assert_allclose(p.tx_position, [-154.0, 64.0, 120.0])
        # Delays are path lengths: never shorter than the straight line, the LOS path exactly it.
        direct = np.linalg.norm(p.rx_position - p.tx_position)
        assert np.all(p.tau_s * SPEED_OF_LIGHT >= direct - 0.01)
        los = np.all(p.interactions == 0, axis=0)
        assert los.any() == row["los"]
        np.testing.assert_allclose(p.tau_s[los] * SPEED_OF_LIGHT, direct, atol=0.01)


def test_deepmimo_loads_the_export_with_the_runs_paths(exported):
    log, paths, folder = exported
    info = json.loads((folder / "caviar.json").read_text())
    assert info["receivers"] == ["uav1", "uav2"] and [s["step"] for s in info["snapshots"]] == [0, 1, 2]
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == ["step_000000", "step_000001", "step_000002"]
    ds = load(folder)
    assert len(ds) == 3
    for snap, step in zip(ds, [0, 1, 2], strict=True):
        assert snap.n_ue == 2
        np.testing.assert_allclose(snap.tx_pos.ravel(), [-154.0, 64.0, 120.0])
        for i, ue in enumerate(["uav1", "uav2"]):
            p = paths[step][ue]
            np.testing.assert_allclose(snap.rx_pos[i], p.rx_position, atol=1e-9)
            b = p.baseband()
            keep = np.argsort(-np.abs(b) ** 2, kind="stable")[: min(25, p.n_paths)]
            n = len(keep)
            assert snap.num_paths[i] == n == info["snapshots"][step]["paths"][ue]["kept"]
            share = np.sum(np.abs(b[keep]) ** 2) / np.sum(np.abs(b) ** 2)
            assert info["snapshots"][step]["paths"][ue]["power_kept"] == pytest.approx(share, abs=1e-6)
            np.testing.assert_allclose(snap.delay[i, :n], p.tau_s[keep], rtol=1e-6)
            np.testing.assert_allclose(snap.power[i, :n], 10 * np.log10(np.abs(b[keep]) ** 2), atol=1e-4)
            np.testing.assert_allclose(np.exp(1j * np.deg2rad(snap.phase[i, :n])), b[keep] / np.abs(b[keep]),
                                       atol=1e-5)
            for name, ours in (("aod_el", p.theta_t), ("aod_az", p.phi_t), ("aoa_el", p.theta_r),
                               ("aoa_az", p.phi_r)):
                np.testing.assert_allclose(snap[name][i, :n], np.rad2deg(ours[keep]), atol=1e-4)
            codes = [int("".join(str(DEEPMIMO_CODE[int(t)]) for t in p.interactions[:, k] if t) or 0) for k in keep]
            assert snap.inter[i, :n].astype(int).tolist() == codes
            depth = p.interactions.shape[0]
            hit = (p.interactions[:, keep] != 0).T  # (n, depth)
            ip = snap.inter_pos[i, :n, :depth]
            np.testing.assert_allclose(ip[hit], np.transpose(p.vertices[:, keep], (1, 0, 2))[hit], atol=1e-3)
            assert np.isnan(ip[~hit]).all()
            assert np.isnan(snap.delay[i, n:]).all()


def deepmimo_channel(snapshot, subcarriers: int, bandwidth_hz: float, k: int) -> np.ndarray:
    """DeepMIMO's own channel of every receiver, single isotropic antennas, at subcarrier k
    (baseband frequency k·bandwidth/subcarriers), without its 1/sqrt(subcarriers) scaling."""
    params = deepmimo.ChannelParameters(
        bs_antenna={"shape": [1, 1], "radiation_pattern": "isotropic"},
        ue_antenna={"shape": [1, 1], "radiation_pattern": "isotropic"},
        ofdm={"subcarriers": subcarriers, "bandwidth": bandwidth_hz, "selected_subcarriers": [k]}, freq_domain=True)
    return snapshot.compute_channels(params)[:, 0, 0, 0] * np.sqrt(subcarriers)


def test_deepmimo_channels_agree_with_the_runs(exported):
    log, paths, folder = exported
    ds = load(folder)
    recorded = {(m.step, m.topic.rsplit(".", 1)[1]): m.data for m in log.decoded("communications.channel.*")}
    for snap, step in zip(ds, [0, 1, 2], strict=True):
        # At the carrier (subcarrier 0): Σ a·exp(−j2π f_c τ) over the 25 strongest paths, computed here.
        at_carrier = deepmimo_channel(snap, 512, 40e6, 0)
        # Where the run recorded H (RECORDED_AT_HZ): k·Δf = RECORDED_AT_HZ with 2^21 subcarriers,
        # wide enough (80 GHz) for delays up to 26 µs.
        n_sc, k = 2**21, 2**20
        at_recorded = deepmimo_channel(snap, n_sc, RECORDED_AT_HZ * n_sc / k, k) if RECORDED_AT_HZ else at_carrier
        for i, ue in enumerate(["uav1", "uav2"]):
            p = paths[step][ue]
            b = p.baseband()
            keep = np.argsort(-np.abs(b) ** 2, kind="stable")[:25]
            dropped = np.sum(np.abs(np.delete(b, keep)))
            assert abs(at_carrier[i] - b[keep].sum()) <= 1e-5 * np.sum(np.abs(b))
            h = recorded[(step, ue)]
            assert h.shape == (1, 1)
            # Sionna computes each path's phase 2π·f·τ in float32 (twice: cir, then cfr), a few
            # ulps of up to 10^6 rad: the bound on the difference; and whatever the 25-path cut dropped.
            ulps = np.sum(np.abs(p.a) * 4 * np.pi * (FC + RECORDED_AT_HZ) * p.tau_s.astype(np.float64) * 2.0**-22)
            assert abs(at_recorded[i] - h[0, 0]) <= ulps + dropped + 1e-3 * abs(h[0, 0]), (step, ue)
            assert abs(at_recorded[i] - h[0, 0]) < 0.1 * abs(h[0, 0])  # measured: 0.4-3.4 %


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Sionna's device orientation: R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    cz, sz, cy, sy, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return rz @ ry @ rx


def elements(rows: int, cols: int, spacing_m: float) -> np.ndarray:
    """A planar array's element offsets in its own frame (the y-z plane), centred, in
    Sionna's order n = i + rows·j: row i along −z, column j along +y
    (docs/paper-era-code.md)."""
    pos = np.array([[0.0, j * spacing_m, -i * spacing_m] for j in range(cols) for i in range(rows)])
    return pos - pos.mean(axis=0)


def test_published_paths_rebuild_the_mimo_channel_of_rotated_arrays():
    """The coefficients at the array centres, with plane-wave phases over the elements of
    the rotated 8x8 and 2x2 arrays computed here, give back sionna-link's H (4 x 64)."""
    cfg = with_raytracing(RadioConfig, samples_per_src=20000, max_depth=2, uav_mesh=False, rx_orientation=[0.7, 0.2,
                                                                                                           -0.3])
    radio = RadioScene(cfg, seed=3)
    radio.keep_paths = True
    radio.place({"a": np.array([-264.0, 176.16, 8.23]), "b": np.array([-134.66, 118.48, 9.23])})
    lam = SPEED_OF_LIGHT / FC
    r_tx = elements(8, 8, 0.5 * lam) @ rotation(*cfg.tx_orientation).T
    r_rx = elements(2, 2, 0.5 * lam) @ rotation(*cfg.rx_orientation).T
    for key, link in radio.solve().items():
        p = link.paths
        assert p is not None and p.n_paths == link.n_paths > 0
        k_t = np.stack([np.sin(p.theta_t) * np.cos(p.phi_t), np.sin(p.theta_t) * np.sin(p.phi_t), np.cos(p.theta_t)])
        k_r = np.stack([np.sin(p.theta_r) * np.cos(p.phi_r), np.sin(p.theta_r) * np.sin(p.phi_r), np.cos(p.theta_r)])
        steer_t = np.exp(2j * np.pi / lam * (r_tx @ k_t))  # (64, P)
        steer_r = np.exp(2j * np.pi / lam * (r_rx @ k_r))  # (4, P)
        coef = p.a * np.exp(-2j * np.pi * (FC + RECORDED_AT_HZ) * p.tau_s.astype(np.float64))
        h = np.einsum("mp,np,p->mn", steer_r, steer_t, coef)
        ulps = np.sum(np.abs(p.a) * 4 * np.pi * (FC + RECORDED_AT_HZ) * p.tau_s.astype(np.float64) * 2.0**-22)
        assert np.max(np.abs(h - link.h)) <= ulps + 1e-3 * np.max(np.abs(link.h)), key
        assert np.linalg.norm(h - link.h) < 0.1 * np.linalg.norm(link.h), key  # measured: 2-3.4 %


def test_in_free_space_the_one_path_is_friis_along_the_straight_line():
    radio = RadioScene(with_raytracing(RadioConfig, scene="empty", uav_mesh=False, max_depth=0, samples_per_src=1000,
                                       pattern="iso",
                                   tx_array=[4, 4], tx_orientation=[0.0, 0.0, 0.0], antenna_offset=[0.0, 0.0, 0.0]))
    radio.keep_paths = True
    radio.place({"far": np.array([300.0, -200.0, 20.0])})
    p = radio.solve()["far"].paths
    d = p.rx_position - p.tx_position
    dist = np.linalg.norm(d)
    assert p.n_paths == 1 and np.all(p.interactions == 0)
    assert p.tau_s[0] * SPEED_OF_LIGHT == pytest.approx(dist, abs=1e-3)
    friis_db = 20 * np.log10(SPEED_OF_LIGHT / FC / (4 * np.pi * dist))  # isotropic elements, matched polarization
    assert 20 * np.log10(abs(p.a[0])) == pytest.approx(friis_db, abs=0.01)
    k = d / dist  # departs along d, arrives from -d
    np.testing.assert_allclose([np.cos(p.theta_t[0]), np.arctan2(k[1], k[0])], [k[2], p.phi_t[0]], atol=1e-5)
    np.testing.assert_allclose([np.cos(p.theta_r[0]), np.arctan2(-k[1], -k[0])], [-k[2], p.phi_r[0]], atol=1e-5)


def test_path_payload_round_trips_and_rejects_garbage():
    p = PathData(a=np.array([1 + 2j], np.complex64), tau_s=np.array([1e-6], np.float32),
                 theta_t=np.ones(1, np.float32), phi_t=np.zeros(1, np.float32), theta_r=np.ones(1, np.float32),
                 phi_r=np.zeros(1, np.float32), interactions=np.array([[1], [8]], np.uint8),
                 vertices=np.zeros((2, 1, 3), np.float32), tx_position=np.zeros(3), rx_position=np.ones(3),
                 frequency_hz=FC, settings={"scene": "x"})
    q = PathData.from_bytes(p.to_bytes())
    assert q.settings == {"scene": "x"} and q.frequency_hz == FC
    for name in ("a", "tau_s", "interactions", "vertices", "rx_position"):
        np.testing.assert_array_equal(getattr(q, name), getattr(p, name))
    with pytest.raises(ValueError, match="step 3: not a path-data payload"):
        PathData.from_bytes(b"not an archive", "step 3")


def test_bad_input_gets_a_clear_error_and_exit_2(exported, cli, tmp_path):
    _, _, folder = exported
    run = folder.parent / "run"
    p = cli("export", "deepmimo", tmp_path / "nowhere", tmp_path / "x", check=2)
    assert "RUN_DIR:" in p.stderr and "nowhere does not exist (expected the folder of a run" in p.stderr
    p = cli("export", "deepmimo", run, folder, check=2)
    assert f"OUT: {folder} already exists" in p.stderr
    p = cli("export", "deepmimo", run, tmp_path / "Scen", check=2)
    assert "lower-case" in p.stderr and "'scen'" in p.stderr
    p = cli("export", "deepmimo", run, tmp_path / "x", "--module", "uav1", check=2)
    assert "module 'uav1' published no path data (those that did: comm)" in p.stderr
    cfg = write_config(tmp_path, config(steps=1, publish_paths=False))
    caviar.Simulation.from_toml(cfg, out=tmp_path / "plain").run()
    p = cli("export", "deepmimo", tmp_path / "plain", tmp_path / "x", check=2)
    assert "no path data" in p.stderr and "--set modules.comm.params.publish_paths=true" in p.stderr
    assert not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="publish_paths needs polarization = 'V' or 'H'"):
        from caviar_plugins.radio import SionnaLinkParams

        SionnaLinkParams(publish_paths=True, polarization="VH")
