"""Beam selection as a reinforcement-learning task (:mod:`caviar.gym`).

The agent plays the beam-selection module of a configuration in which it runs before the
communications module (``blueprints/beam-gym``), one agent per UAV:

* observation: ``{"position": (x, y, z)}`` of the UAV this step (scene frame, m) and, with
  ``previous_gains``, ``"previous_gains"``: the gains of all pairs of the previous step's
  beam sweep (``communications.beam_gains.<UE_Id>``), divided by their maximum (zeros at
  the first step);
* action: the beam pair (``Discrete(256)``: rx_beam · 64 + tx_beam), published on
  ``ai.beam.selection`` as the ``beam-selector`` plugin does;
* reward: the UAV's throughput with that pair divided by the throughput of the best pair
  of the step (``communications.throughput`` / ``communications.link``'s
  ``best_throughput``), in [0, 1]; ``info``: ``top1`` (the pair is the best one), the
  pair, the best pair, both throughputs (Mbit/s) and the LOS flag.

    spec = beam_selection_spec("uav1", previous_gains=True)
    env = caviar.gym.make("blueprints/beam-gym/config.toml", agent="beams", spec=spec)
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from gymnasium import spaces

from caviar.gym import AgentSpec
from caviar.plugin import Inbox, Message
from caviar_plugins.schema import BEAM_GAINS, BEAM_SELECTION, LINK, POSITIONS, THROUGHPUT, per_ue

PAIRS = 256
"""Beam pairs of the link's codebooks (4 Rx × 64 Tx beams)."""
SCENE_BOUND_M = 1.0e4
"""Positions are in [-10 km, 10 km] on every axis."""


def observe_position(inbox: Inbox, ue: str) -> np.ndarray:
    """The UAV's latest position in the inbox, as float32 (x, y, z)."""
    for m in reversed(inbox.on(POSITIONS)):
        if m.data["UE_Id"] == ue:
            p = m.data["position"]
            return np.array([p["x"], p["y"], p["z"]], dtype=np.float32)
    raise ValueError(f"no position of UE '{ue}' on {POSITIONS} in the agent module's inbox (step "
                     f"{inbox[0].step if len(inbox) else '?'}): is it the UE_Id of a mobility module?")


def observe_gains(inbox: Inbox, ue: str, pairs: int = PAIRS) -> np.ndarray:
    """The UAV's latest beam sweep in the inbox divided by its maximum (float32), zeros if none."""
    m = inbox.latest(per_ue(BEAM_GAINS, ue))
    if m is None:
        return np.zeros(pairs, dtype=np.float32)
    gains = np.asarray(m.data, dtype=np.float64).ravel()
    if gains.size != pairs:
        raise ValueError(f"{m.topic}: expected the gains of {pairs} beam pairs, got {gains.size}")
    top = float(gains.max())
    return (gains / top if top > 0 else np.zeros(pairs)).astype(np.float32)


def link_of(messages: Sequence[Message], ue: str) -> dict[str, Any] | None:
    """The UAV's last ``communications.link`` payload among ``messages``."""
    for m in reversed(messages):
        if m.topic == LINK and m.data["UE_Id"] == ue:
            return m.data
    return None


def throughput_of(messages: Sequence[Message], ue: str) -> float | None:
    """The UAV's last throughput (Mbit/s) among ``messages``."""
    for m in reversed(messages):
        if m.topic == THROUGHPUT and m.data["UE_Id"] == ue:
            return float(m.data["throughput"])
    return None


def beam_selection_spec(ue: str = "uav1", previous_gains: bool = False, pairs: int = PAIRS) -> AgentSpec:
    """The beam-selection agent of UE ``ue`` (see the module's docstring)."""
    parts: dict[str, spaces.Space] = {
        "position": spaces.Box(-SCENE_BOUND_M, SCENE_BOUND_M, (3,), np.float32)}
    topics = [POSITIONS]
    if previous_gains:
        parts["previous_gains"] = spaces.Box(0.0, 1.0, (pairs,), np.float32)
        topics.append(per_ue(BEAM_GAINS, ue))

    def observe(inbox: Inbox) -> dict[str, np.ndarray]:
        obs = {"position": observe_position(inbox, ue)}
        if previous_gains:
            obs["previous_gains"] = observe_gains(inbox, ue, pairs)
        return obs

    def act(action: Any) -> list[tuple[str, Any]]:
        return [(BEAM_SELECTION, {"UE_Id": ue, "beam_pair": int(action)})]

    def reward(messages: Sequence[Message]) -> float:
        link, mbps = link_of(messages, ue), throughput_of(messages, ue)
        if link is None or mbps is None or link["best_throughput"] <= 0:
            return 0.0
        return mbps / float(link["best_throughput"])

    def info(messages: Sequence[Message]) -> dict[str, Any]:
        link, mbps = link_of(messages, ue), throughput_of(messages, ue)
        if link is None or mbps is None:
            return {}
        return {"top1": bool(link["pair"] == link["best_pair"]), "pair": int(link["pair"]),
                "best_pair": int(link["best_pair"]), "throughput_mbps": mbps,
                "best_throughput_mbps": float(link["best_throughput"]), "los": bool(link["los"])}

    return AgentSpec(subscribe=tuple(topics), observation_space=spaces.Dict(parts),
                     action_space=spaces.Discrete(pairs), observe=observe, act=act, reward=reward, info=info)
