"""The per-UE link report that ``sionna-link`` and ``sionna-traffic-link`` share
(:mod:`caviar_plugins.radio.link_report`), checked against independent computations
(no ray tracing: paths and links are made up here)."""

import math

import numpy as np
import pytest
from scipy.constants import c

import caviar
from caviar_plugins.radio.link_report import LINK_TOPICS, db, line_of_sight_paths, link_messages
from caviar_plugins.radio.scene import Link
from caviar_plugins.radio.sionna_link import SionnaLink
from caviar_plugins.schema import BEAM_GAINS, CHANNEL, LINK, STATE, THROUGHPUT
from caviar_plugins.traffic.link import SionnaTrafficLink

TX = np.array([0.0, 0.0, 25.0])
RX = np.array([[80.0, 30.0, 1.6], [-40.0, 60.0, 10.0]])


def test_the_line_of_sight_path_is_the_one_as_long_as_the_straight_line():
    direct = np.linalg.norm(RX - TX, axis=1)
    ground = np.linalg.norm(RX - TX * [1, 1, -1], axis=1)  # reflected by z = 0: the image source
    # Per receiver: the direct path, the ground reflection, a path 5 mm and one 2 cm longer than the direct one.
    length = np.stack([direct, ground, direct + 0.005, direct + 0.02], axis=1)
    tau = length / c
    valid = np.array([[True, True, True, True], [False, True, True, True]])  # receiver 2: no direct path found
    expected = [[True, False, True, False], [False, False, True, False]]
    assert line_of_sight_paths(tau, valid, direct[:, None]).tolist() == expected  # all receivers (RadioScene)
    for i in range(len(RX)):  # one receiver, its distance a float (sionna-traffic-link)
        assert line_of_sight_paths(tau[i], valid[i], float(direct[i])).tolist() == expected[i]


def test_db_is_ten_log10_and_minus_400_for_no_gain():
    assert db(1e-3) == pytest.approx(-30.0) and type(db(np.float32(2.0))) is float
    assert db(0.0) == -400.0 and db(-1.0) == -400.0


def _link(paths_dropped=0) -> Link:
    rng = np.random.default_rng(1)
    h = (rng.normal(size=(2, 3)) + 1j * rng.normal(size=(2, 3))) * 1e-4
    gains = np.array([[1e-9, 4e-8, 2e-9], [3e-9, 1e-8, 5e-9]], dtype=np.float32)
    return Link(h=h, gains=gains, los=True, n_paths=7, paths_dropped=paths_dropped)


def _mbps(gain: float) -> float:
    return 40 * math.log2(1 + 1e9 * gain)


def _snr(gain: float) -> float:
    return 1e9 * gain


def test_link_messages_report_the_used_pair_then_the_link_then_h_and_the_gains():
    link = _link()
    msgs = list(link_messages("car", "car1", link, None, 6, _mbps, _snr, True, {"speed": 3.0, "blocker": None}))
    assert [topic for topic, _ in msgs] == [THROUGHPUT, LINK, f"{CHANNEL}.car1", f"{BEAM_GAINS}.car1"]
    assert all(any(caviar.matches(p, topic) for p in LINK_TOPICS) for topic, _ in msgs)
    best = float(np.float32(4e-8))  # no pair selected: the strongest, flat index 1
    assert msgs[0][1] == {"UE_type": "car", "UE_Id": "car1", "throughput": _mbps(best)}
    payload = msgs[1][1]
    # the recorded JSON's order
    assert list(payload) == ["UE_type", "UE_Id", "los", "n_paths", "best_pair", "pair", "selected",
                             "path_gain_db", "pair_gain_db", "snr_db", "best_throughput", "speed", "blocker"]
    assert payload["pair"] == payload["best_pair"] == 1 and payload["selected"] is False
    assert payload["path_gain_db"] == pytest.approx(10 * math.log10(np.mean(np.abs(link.h) ** 2)), rel=1e-12)
    assert payload["snr_db"] == pytest.approx(10 * math.log10(1e9 * best), rel=1e-12)
    assert payload["pair_gain_db"] == pytest.approx(10 * math.log10(best), rel=1e-12)  # the used pair's
    assert payload["best_throughput"] == _mbps(best) and payload["speed"] == 3.0 and payload["blocker"] is None
    assert msgs[2][1].dtype == np.complex64 and np.allclose(msgs[2][1], link.h)
    assert msgs[3][1].dtype == np.float32 and np.array_equal(msgs[3][1], link.gains)


def test_a_selected_pair_is_used_and_dropped_paths_come_last():
    msgs = list(link_messages("UAV", "uav1", _link(paths_dropped=5), 5, 6, _mbps, _snr, False, {"speed": 0.0}))
    assert [topic for topic, _ in msgs] == [THROUGHPUT, LINK]  # no channels
    assert msgs[0][1]["throughput"] == _mbps(float(np.float32(5e-9)))
    payload = msgs[1][1]
    assert payload["pair"] == 5 and payload["best_pair"] == 1 and payload["selected"] is True
    assert list(payload)[-2:] == ["speed", "paths_dropped"] and payload["paths_dropped"] == 5
    with pytest.raises(ValueError, match="beam pair 6 for uav1 is outside 0..5"):
        list(link_messages("UAV", "uav1", _link(), 6, 6, _mbps, _snr, False))


@pytest.mark.parametrize("plugin, own", [(SionnaLink, ("communications.prediction", "communications.paths.*",
                                                       "caviar.status")),
                                         (SionnaTrafficLink, ("caviar.status",))])
def test_both_link_plugins_declare_what_the_report_publishes(plugin, own):
    assert plugin.publishes == (*LINK_TOPICS, STATE, *own)
