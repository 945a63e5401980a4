"""What a ray-traced link plugin publishes per UE and step, in one place: ``sionna-link``
and ``sionna-traffic-link`` both report through :func:`link_messages`, and find the
line-of-sight path by its length with :func:`line_of_sight_paths`."""

from __future__ import annotations

from typing import Any, Callable, Iterator, Mapping

import numpy as np

from caviar_plugins.radio.link_budget import SPEED_OF_LIGHT
from caviar_plugins.schema import BEAM_GAINS, CHANNEL, LINK, THROUGHPUT, every_ue, per_ue, throughput_payload

LINK_TOPICS = (THROUGHPUT, LINK, every_ue(CHANNEL), every_ue(BEAM_GAINS))
"""What :func:`link_messages` publishes: a link plugin's ``publishes`` are these and its own."""

LOS_TOLERANCE_M = 0.01
"""A path is the line of sight when it is as long as the straight line, to 1 cm (cheaper
than asking the solver for every path's interaction types)."""


def db(x: float) -> float:
    """10·log10(x), or -400 dB for a zero gain."""
    return float(10 * np.log10(x)) if x > 0 else -400.0


def line_of_sight_paths(tau_s: np.ndarray, valid: np.ndarray, direct_m: np.ndarray | float) -> np.ndarray:
    """Which paths are the direct one: valid, and as long (delay × c) as the straight line
    ``direct_m`` (broadcast against ``tau_s``'s leading axes)."""
    return valid & (np.abs(np.asarray(tau_s) * SPEED_OF_LIGHT - direct_m) < LOS_TOLERANCE_M)


def link_messages(ue_type: str, ue: str, link: Any, pair: int | None, n_pairs: int,
                  mbps: Callable[[float], float], snr: Callable[[float], float], publish_channels: bool,
                  extra: Mapping[str, Any] | None = None,
                  throughput_mbps: float | None = None) -> Iterator[tuple[str, Any]]:
    """The messages of one UE's link (a :class:`~caviar_plugins.radio.scene.Link`): its
    throughput (the paper's schema), ``communications.link`` (its fields, then ``extra``)
    and, with ``publish_channels``, H and the beam-pair gains. ``pair``: the beam pair the
    AI module selected, None for the link's best; ``mbps`` and ``snr`` turn a beam-pair
    gain into Mbit/s and a linear SNR. ``throughput_mbps``: the UE's throughput when a
    link level computed it (instead of ``mbps`` of the used pair)."""
    selected = pair is not None
    if pair is None:
        pair = link.best_pair
    if not 0 <= pair < n_pairs:
        raise ValueError(f"beam pair {pair} for {ue} is outside 0..{n_pairs - 1}")
    gain = float(link.gains.flat[pair])
    yield THROUGHPUT, throughput_payload(ue_type, ue, mbps(gain) if throughput_mbps is None else throughput_mbps)
    payload = {
        "UE_type": ue_type, "UE_Id": ue, "los": link.los, "n_paths": link.n_paths,
        "best_pair": link.best_pair, "pair": pair, "selected": selected,
        "path_gain_db": db(link.path_gain), "pair_gain_db": db(gain), "snr_db": db(snr(gain)),
        "best_throughput": mbps(float(link.gains.max())),
        **(extra or {}),
    }
    if getattr(link, "paths_dropped", 0):  # only when Sionna's path buffer overflowed (sionna#1172)
        payload["paths_dropped"] = link.paths_dropped
    yield LINK, payload
    if publish_channels:
        yield per_ue(CHANNEL, ue), link.h.astype(np.complex64)
        yield per_ue(BEAM_GAINS, ue), link.gains.astype(np.float32)
