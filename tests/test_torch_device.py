"""PyTorch on one device, chosen in one place (issue #39, part 1), caught on a CPU-only
machine: the radio network's link level (Sionna SYS) runs its slots under a guard that
fails any torch operation whose tensors are not all on the chosen device and any numpy
crossing outside ``caviar_plugins.torch_device`` (the mistake that stopped the network at
its first slot on an H100: a numpy-made CPU tensor beside Sionna's on ``cuda:0``)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from caviar_plugins.network.traffic import Backlog  # noqa: E402
from caviar_plugins.radio.link_level import LinkLevel  # noqa: E402
from caviar_plugins.radio.link_settings import LinkSettings  # noqa: E402
from caviar_plugins.torch_device import DeviceGuard, check_setting, resolve, to_numpy, to_torch  # noqa: E402


def slots(level: LinkLevel, n_ue: int, n_slots: int, subbands: int, seed: int = 0, queued: bool = False):
    """``n_slots`` slots of random SINRs; ``queued``: a backlog (some UEs with bits at the
    start, one whose bits arrive halfway), else full buffers."""
    rng = np.random.default_rng(seed)
    sinr = rng.uniform(-5.0, 25.0, (n_slots, n_ue, subbands))
    serving = np.arange(n_ue) % level.n_cell
    backlog = None
    if queued:
        arrivals = np.zeros((n_slots, n_ue))
        arrivals[n_slots // 2, 0] = 40e3
        backlog = Backlog(queued_bits=np.where(np.arange(n_ue) % 2 == 1, 1e5, 0.0), arrivals_bits=arrivals)
    return level.run(sinr, serving, backlog=backlog)


@pytest.mark.parametrize("scheduler, subbands", [("proportional-fair", 4), ("round-robin", 1), ("max-rate", 2)])
def test_the_link_level_keeps_every_tensor_on_its_device_and_crosses_numpy_in_one_place(scheduler, subbands):
    settings = LinkSettings(num_prb=24, subcarrier_spacing_hz=30e3, scheduler=scheduler, harq_processes=2,
                            subbands=subbands, device="cpu")
    level = LinkLevel(settings, n_cell=3, seed=1, capacity=2)
    assert level.device == torch.device("cpu")
    with DeviceGuard("cpu") as guard:
        first = slots(level, n_ue=3, n_slots=4, subbands=subbands)
        queued = slots(level, n_ue=3, n_slots=8, subbands=subbands, queued=True)
        level.moved(0, 1)
        level.released(2)
        grown = slots(level, n_ue=6, n_slots=4, subbands=subbands)  # more UEs than capacity: it grows
        state = level.state()
        level.restore(state)
    assert guard.operations > 100
    assert level.capacity >= 6 and first.decoded_bits.sum() > 0 and grown.decoded_bits.sum() > 0
    assert queued.decoded_bits[0] > 0 and queued.delivered_bits[:4, 0].sum() == 0  # its bits came halfway
    # The same slots without the guard: the guard changes nothing.
    again = LinkLevel(settings, n_cell=3, seed=1, capacity=2)
    np.testing.assert_array_equal(slots(again, 3, 4, subbands).decoded_bits, first.decoded_bits)


def test_the_guard_catches_a_numpy_made_tensor_and_a_second_device():
    with pytest.raises(AssertionError, match="torch.tensor of a numpy array outside"):
        with DeviceGuard("cpu"):
            torch.tensor(np.zeros(3))
    with pytest.raises(AssertionError, match=r"Tensor.numpy\(\) outside"):
        with DeviceGuard("cpu"):
            torch.zeros(3).numpy()
    with pytest.raises(AssertionError, match=r"torch add: operands on \['cpu', 'meta'\], expected all on cpu"):
        with DeviceGuard("cpu"):
            torch.add(torch.zeros(3), torch.zeros(3, device="meta"))
    with DeviceGuard("cpu"):  # the helpers are the way across
        t = to_torch(np.arange(3.0), "cpu", torch.float32)
        assert to_numpy(t * 2).tolist() == [0.0, 2.0, 4.0]


def test_auto_is_sionnas_device_and_a_bad_setting_is_named():
    import sionna.phy

    assert resolve("auto") == torch.device(sionna.phy.config.device)
    assert resolve("cpu") == torch.device("cpu")
    for bad in ("gpu", "cuda:x", "tpu:0"):
        with pytest.raises(ValueError, match=rf"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got '{bad}'"):
            check_setting(bad)
    with pytest.raises(ValueError, match="device: expected"):
        LinkSettings(num_prb=24, device="gpu")


def test_the_link_levels_checkpoint_holds_the_schedulers_rate_history(monkeypatch):
    """The proportional-fair scheduler keeps its rate history in torch buffers, which an
    object's attributes do not show: a checkpoint without them resumed a cell of several UEs
    with a fresh history (a one-site network did not resume bit for bit). Restored into a new
    link level, the state gives the next slots exactly as the original goes on."""
    import pickle

    from caviar_plugins.radio import sionna_sys_adapter

    settings = LinkSettings(num_prb=24, subcarrier_spacing_hz=30e3, harq_processes=2, subbands=2, device="cpu")
    sinr = np.random.default_rng(3).uniform(0.0, 20.0, (8, 3, 2))
    serving = np.zeros(3, dtype=int)  # three UEs in one cell: the scheduler's history decides

    def resumed(state_of):
        a = LinkLevel(settings, n_cell=1, seed=4)
        a.run(sinr[:4], serving)
        b = LinkLevel(settings, n_cell=1, seed=4)
        b.restore(pickle.loads(pickle.dumps(state_of(a))))
        return a.run(sinr[4:], serving), b.run(sinr[4:], serving)

    going_on, back = resumed(LinkLevel.state)
    assert "_rate_achieved_past" in LinkLevel(settings, n_cell=1, seed=4).state()["pf"]
    np.testing.assert_array_equal(back.decoded_bits, going_on.decoded_bits)
    np.testing.assert_array_equal(back.prbs, going_on.prbs)
    # Without the buffers (attributes only, as before) the resumed slots differ.
    monkeypatch.setattr(sionna_sys_adapter, "block_state", lambda block: {
        k: v.clone() for k, v in vars(block).items() if isinstance(v, torch.Tensor)})
    going_on, back = resumed(LinkLevel.state)
    assert not np.array_equal(back.prbs, going_on.prbs)


@pytest.mark.parametrize("scheduler", ["proportional-fair", "round-robin", "max-rate"])
@pytest.mark.parametrize("queued", [False, True])
def test_the_slots_cross_between_numpy_and_torch_once_per_call_not_once_per_slot(monkeypatch, scheduler, queued):
    """Sionna SYS on the GPU (#39 part 3): a call's SINRs enter torch once and its results
    leave once, however many slots it runs; a crossing per slot would copy to and from a GPU,
    and wait for it, at every slot. The schedulers and the queues work on the device."""
    import caviar_plugins.radio.link_level as link_level

    crossings = {"in": 0, "out": 0}

    def counted(helper, way):
        def crossing(*args, **kwargs):
            crossings[way] += 1
            return helper(*args, **kwargs)
        return crossing

    monkeypatch.setattr(link_level, "to_torch", counted(to_torch, "in"))
    monkeypatch.setattr(link_level, "to_numpy", counted(to_numpy, "out"))
    settings = LinkSettings(num_prb=24, subcarrier_spacing_hz=30e3, scheduler=scheduler, harq_processes=2,
                            subbands=2, device="cpu")
    level = LinkLevel(settings, n_cell=2, seed=1, capacity=4)
    per_call = []
    for n_slots in (4, 40):
        crossings.update({"in": 0, "out": 0})
        result = slots(level, n_ue=4, n_slots=n_slots, subbands=2, queued=queued)
        assert result.decoded_bits.sum() > 0 and result.delivered_bits.shape == (n_slots, 4)
        per_call.append(dict(crossings))
    assert per_call[0] == per_call[1], f"crossings grow with the slots: {per_call}"
    assert per_call[1]["in"] <= 4 and per_call[1]["out"] <= 10


def test_round_robin_and_max_rate_grant_as_their_definitions_say():
    """The device-side schedulers against their definitions, computed by hand: round-robin
    gives slot k of a cell to its members in turn (the (k mod n)-th), max-rate each subband
    to the member of best SINR; a cell without members grants nothing."""
    sinr = np.array([[10.0, 20.0, 5.0, 0.0], [30.0, 1.0, 2.0, 3.0]])  # [subband, UE] dB, every slot
    serving = np.array([0, 0, 0, -1])  # three UEs in cell 0, one without a cell; cell 1 empty
    for scheduler in ("round-robin", "max-rate"):
        settings = LinkSettings(num_prb=24, subcarrier_spacing_hz=30e3, scheduler=scheduler, harq_processes=2,
                                subbands=2, device="cpu")
        level = LinkLevel(settings, n_cell=2, seed=1, capacity=4)
        res = level.run(np.broadcast_to(sinr.T[None], (6, 4, 2)).copy(), serving)
        assert res.cells_active[:, 0].all() and not res.cells_active[:, 1].any()
        if scheduler == "round-robin":  # slots 0..5: UEs 0, 1, 2, 0, 1, 2, all 24 PRBs each
            np.testing.assert_array_equal(res.scheduled_slots, [2, 2, 2, 0])
            np.testing.assert_array_equal(res.prbs, [48, 48, 48, 0])
        else:  # subband 0 (12 PRBs) to UE 1 (20 dB), subband 1 (12 PRBs) to UE 0 (30 dB), 6 slots
            np.testing.assert_array_equal(res.scheduled_slots, [6, 6, 0, 0])
            np.testing.assert_array_equal(res.prbs, [72, 72, 0, 0])


def test_numpy_products_beside_torch_run_on_one_blas_thread_and_the_setting_comes_back():
    """The radio network's numpy products run under ``one_blas_thread``: OpenBLAS's idle
    threads would otherwise spin on the cores Sionna SYS needs next (1.3x slower SYS calls on
    2 cores). Inside, every BLAS library has one thread; after, what it had."""
    from threadpoolctl import threadpool_info

    from caviar_plugins.torch_device import one_blas_thread

    def blas_threads():
        return [(i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    assert before, "numpy has a BLAS library"
    with one_blas_thread():
        assert {n for _, n in blas_threads()} == {1}
        np.ones((64, 64)) @ np.ones((64, 64))
    assert blas_threads() == before


def network_step(device, n_slot: int = 30):
    """A step's channel arithmetic of the radio network on ``device``: 4 cells (3 on one
    carrier, one of them serving nobody; 1 on another), 7 UEs (one unserved; one with nothing
    to send, so its cell hears nobody in the uplink). Returns the inputs and the results."""
    from caviar_plugins.network.beams import Codebook, beam_responses, gains_of_responses, scheduled_ues, slot_sinr_db
    from caviar_plugins.network.cells import Cell
    from caviar_plugins.network.raytraced import TracedChannels, summed_db
    from caviar_plugins.network.uplink import slot_sinr_db as uplink_sinr_db

    rng = np.random.default_rng(5)
    n_ue, n_cell, n_path, n_f = 7, 4, 4, 2
    cells = [Cell(name=f"c{k}", site=f"s{k}", index=k, position=(100.0 * k, 0.0, 25.0), azimuth_deg=60.0 * k,
                  downtilt_deg=4.0, tx_power_dbm=40.0 + k, carrier_hz=3.5e9 if k < 3 else 2.1e9, bandwidth_hz=20e6,
                  array=(2, 4)) for k in range(n_cell)]
    arrival = rng.normal(size=(n_ue, n_cell, n_path, 3))
    arrival /= np.linalg.norm(arrival, axis=-1, keepdims=True)
    channels = TracedChannels(amplitude=(rng.normal(size=(n_ue, n_cell, n_path)) + 1j) * 1e-5,
                              delay_s=rng.uniform(0, 1e-6, (n_ue, n_cell, n_path)), arrival=arrival,
                              position=rng.uniform(-50, 50, (n_ue, 3)), carrier_hz=3.5e9,
                              power_sum_db=np.zeros((n_ue, n_cell)), departure=-arrival)
    x = {"channels": channels, "cells": cells, "moved": channels.position + rng.normal(size=(n_ue, 3)),
         "f": np.array([-5e6, 5e6]), "serving": np.array([0, 1, 3, -1, 0, 1, 0]), "best": rng.integers(0, 4, n_ue),
         "noise": np.full(n_ue, 1e-12), "desired": rng.exponential(1e-9, (n_ue, n_f)),
         "ul_gains": rng.exponential(1e-11, (n_ue, n_cell, n_f, 3)), "receive": rng.integers(0, 3, n_ue),
         "power": rng.uniform(-10.0, 10.0, n_ue),
         "carriers": np.array([c.carrier_hz for c in cells])}
    x["pointed"] = scheduled_ues(x["serving"], n_cell, n_slot)  # (cell 2 serves nobody: -1)
    x["beams_of"] = np.where(x["pointed"] >= 0, x["best"][np.maximum(x["pointed"], 0)], -1)
    x["heard"] = scheduled_ues(np.where(np.arange(n_ue) == 1, -1, x["serving"]), n_cell, n_slot)  # UE 1: silent
    amplitude = channels.amplitudes_on(device, x["moved"], x["f"])
    gains = gains_of_responses(amplitude, beam_responses(cells, [Codebook(2, 4, 4)] * n_cell, -arrival, device))
    return x, {"amplitude": amplitude, "gains_db": summed_db(amplitude), "gains": gains,
               "downlink": slot_sinr_db(cells, gains, x["serving"], x["best"], x["beams_of"], x["noise"],
                                        silent_idle=False, device=device),
               "uplink": uplink_sinr_db(x["desired"], x["ul_gains"], x["receive"], x["serving"], x["carriers"],
                                        x["power"], x["heard"], 1e-13, device=device)}


def test_the_networks_per_step_channel_arithmetic_stays_on_a_second_device(monkeypatch):
    """On a device that is not the host's (``meta``: shapes without values), every operation
    of a step's channel arithmetic stays there and numpy crosses only through the helpers:
    the mistakes that would stop it on a GPU fail here."""
    from caviar_plugins import torch_device
    from caviar_plugins.network import beams, raytraced

    def shaped(tensor):  # (a meta tensor has no values to read)
        assert tensor.device.type == "meta"
        return np.zeros(tuple(tensor.shape))

    for module in (torch_device, beams, raytraced):
        monkeypatch.setattr(module, "to_numpy", shaped)
    with DeviceGuard("meta") as guard:
        _, out = network_step(torch.device("meta"))
    assert guard.operations > 20
    assert out["amplitude"].device.type == "meta" and out["downlink"].shape == (30, 7, 2) == out["uplink"].shape


def test_the_networks_per_step_channel_arithmetic_equals_the_sums_by_hand():
    """A step's channel at scale (the paths moved, their beam gains, the downlink's and the
    uplink's per-slot SINR) as torch computes it on the link level's device, against the sums
    written out by hand, UE by UE and cell by cell."""
    with DeviceGuard("cpu") as guard:
        x, out = network_step(torch.device("cpu"))
    assert guard.operations > 20
    ch, f, serving, best, gains = x["channels"], x["f"], x["serving"], x["best"], out["gains"]
    # By hand: each path's phase, summed over paths.
    shorter = np.einsum("ucpk,uk->ucp", ch.arrival, x["moved"] - ch.position)
    a = ch.amplitude[..., None] * np.exp(2j * np.pi * ((3.5e9 + f) * shorter[..., None] / 299_792_458.0
                                                       - ch.delay_s[..., None] * f))
    np.testing.assert_allclose(to_numpy(out["amplitude"]), a, rtol=1e-9)
    np.testing.assert_allclose(out["gains_db"], 10 * np.log10(np.abs(a.sum(axis=2)) ** 2), rtol=1e-9)
    # By hand: the downlink, victim by victim, the other cells on its carrier pointing their beam (or
    # sending over their codebook evenly when they serve nobody); the uplink, the UE each other cell hears.
    p_cell = 10 ** (np.array([c.tx_power_dbm for c in x["cells"]]) / 10)
    p_ue, carriers, beams_of, heard = 10 ** (x["power"] / 10), x["carriers"], x["beams_of"], x["heard"]
    assert (beams_of[:, 2] == -1).all() and (heard == -1).any()  # (an idle cell; a cell hearing nobody)
    for u in range(len(serving)):
        s = serving[u]
        if s < 0:
            assert np.isnan(out["downlink"][:, u]).all() and np.isnan(out["uplink"][:, u]).all()
            continue
        for k in range(len(beams_of)):
            others = [c for c in range(len(carriers)) if c != s and carriers[c] == carriers[s]]
            dl_i = sum(p_cell[c] * (gains[u, c, :, beams_of[k, c]] if beams_of[k, c] >= 0 else gains[u, c].mean(-1))
                       for c in others)
            np.testing.assert_allclose(out["downlink"][k, u], 10 * np.log10(p_cell[s] * gains[u, s, :, best[u]]
                                                                            / (x["noise"][u] + dl_i)), rtol=1e-9)
            ul_i = sum(p_ue[heard[k, c]] * x["ul_gains"][heard[k, c], s, :, x["receive"][u]]  # (into u's beam)
                       for c in others if heard[k, c] >= 0)
            np.testing.assert_allclose(out["uplink"][k, u], 10 * np.log10(p_ue[u] * x["desired"][u] / (1e-13 + ul_i)),
                                       rtol=1e-9)
