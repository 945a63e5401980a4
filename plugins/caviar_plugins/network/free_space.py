"""The ``free-space`` channel: Friis along the straight line with each cell's sector pattern
(:func:`~caviar_plugins.network.cells.line_of_sight_gain_db`), flat in frequency, and SSB
beams on the line of sight (:func:`~caviar_plugins.network.beams.line_of_sight`)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from caviar_plugins.network.beams import all_beam_gains, line_of_sight
from caviar_plugins.network.cells import Cell, line_of_sight_gain_db
from caviar_plugins.network.channel import UePlaces


class FreeSpaceChannel:
    kind = "free-space"
    directions = True
    flat = True

    def __init__(self, cells: Sequence[Cell]):
        self.cells = list(cells)

    def gains_db(self, t: float, ues: UePlaces) -> np.ndarray:
        return line_of_sight_gain_db(self.cells, ues.positions)[..., None]

    def beam_gains(self, ues: UePlaces, codebooks: Sequence[Any]) -> np.ndarray:
        amplitude, departure = line_of_sight(self.cells, ues.positions)
        return all_beam_gains(self.cells, codebooks, amplitude[..., None], departure)

    def forget(self, ue: str) -> None:
        pass

    def outdoors(self, points: np.ndarray) -> np.ndarray:
        return np.ones(len(points), dtype=bool)

    def state(self) -> None:
        return None

    def restore(self, state: Any) -> None:
        pass
