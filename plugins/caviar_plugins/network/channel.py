"""The radio network's channel: one protocol, :class:`Channel`, and its three models, each in
a module of its own and chosen once at set-up by
:func:`~caviar_plugins.network.settings.make_channel`:

* ``free-space``: :class:`~caviar_plugins.network.free_space.FreeSpaceChannel` (Friis and the
  sector pattern along the straight line);
* ``ray-traced``: :class:`~caviar_plugins.network.traced_channel.RayTracedChannel` (Sionna RT,
  every site in one solve, evolved between traces);
* ``38.901-uma``, ``38.901-umi``, ``38.901-rma``:
  :class:`~caviar_plugins.network.tr38901.Tr38901Channel` (Sionna's stochastic models).

The network asks a channel for gains (and, where it knows the paths' directions, for SSB
beam gains); it never asks which channel it has.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol, Sequence

import numpy as np


@dataclasses.dataclass
class UePlaces:
    """Where the step's UEs are: ``ids``, antenna ``positions`` [ue, 3] (m), and for the
    stochastic models whether each is ``indoor`` [ue] and how far inside
    (``distance_2d_in`` [ue], m)."""

    ids: list[str]
    positions: np.ndarray
    indoor: np.ndarray
    distance_2d_in: np.ndarray


class Channel(Protocol):
    """What the network needs of a channel model."""

    kind: str
    """The ``channel`` setting it answers to."""
    directions: bool
    """Whether it knows the directions paths leave the cells in (what SSB beams need)."""
    flat: bool
    """Whether it is flat in frequency (one value for the whole band)."""

    def gains_db(self, t: float, ues: UePlaces) -> Any:
        """Channel gains (path and sector pattern, dB) of every cell toward ``ues`` at virtual
        time ``t``: [ue, cell, frequency] (one frequency when :attr:`flat`). numpy, or a
        float64 tensor on the network's torch device where the channel computes there (the
        network reads only what it needs of it: :func:`~caviar_plugins.network.downlink.received`)."""
        ...

    def beam_gains(self, ues: UePlaces, codebooks: Sequence[Any]) -> Any:
        """[ue, cell, frequency, beam]: every cell's SSB beams toward ``ues`` (linear), for the
        places of the last :meth:`gains_db` (only where :attr:`directions`); numpy, or a
        float64 tensor on the network's torch device."""
        ...

    def forget(self, ue: str) -> None:
        """Drops what the channel keeps of UE ``ue`` (it left; a UE of its name later is new)."""
        ...

    def outdoors(self, points: np.ndarray) -> np.ndarray:
        """Whether each point [n, 3] stands under open sky (no scene: all of them)."""
        ...

    def state(self) -> Any:
        """What a checkpoint keeps (picklable)."""
        ...

    def restore(self, state: Any) -> None:
        ...
