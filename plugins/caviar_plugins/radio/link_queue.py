"""One link-level call's bits per UE (:class:`CallQueue`): what the
:class:`~caviar_plugins.radio.link_level.LinkLevel` may serve in its slots, on the host or on
its torch device, and what each slot delivered."""

from __future__ import annotations

from typing import Any

import numpy as np

from caviar_plugins.torch_device import to_torch


class CallQueue:
    """One call's bits per UE: what is queued (full buffer: unbounded), what arrives at each
    slot, and what each slot delivered."""

    def __init__(self, n_slots: int, n_ue: int, backlog: Any):
        self.finite = backlog is not None
        self.left = np.full(n_ue, np.inf) if backlog is None else np.asarray(backlog.queued_bits, float).copy()
        self.arrivals = None if backlog is None else np.asarray(backlog.arrivals_bits, float)
        if self.arrivals is not None and self.arrivals.shape != (n_slots, n_ue):
            raise ValueError(f"backlog: expected arrivals of shape {(n_slots, n_ue)}, got {self.arrivals.shape}")
        self.arrived_to = -1  # the last slot whose arrivals are in self.left
        self.delivered = np.zeros((n_slots, n_ue))
        self._minimum: Any = lambda bits, left: np.minimum(np.asarray(bits, float), left)

    def on_device(self, device: Any, torch: Any, cap: int) -> None:
        """The queue's arrays as float64 tensors on ``device``, ``cap`` columns wide (the SYS
        loop's; the columns past the call's UEs have nothing queued)."""
        n_slots, n_ue = self.delivered.shape
        pad = ((0, cap - n_ue),)
        self.left = to_torch(np.pad(self.left, pad), device, torch.float64)  # (a full buffer: eligible throughout)
        if self.arrivals is not None:
            self.arrivals = to_torch(np.pad(self.arrivals, ((0, 0), *pad)), device, torch.float64)
        if self.finite:  # (a full buffer delivers what it decodes: no copy kept)
            self.delivered = torch.zeros((n_slots, cap), dtype=torch.float64, device=device)
        self._minimum = torch.minimum

    def _arrive(self, slot: int) -> None:
        if self.arrivals is not None:
            while self.arrived_to < slot:
                self.arrived_to += 1
                self.left += self.arrivals[self.arrived_to]

    def eligible(self, slot: int) -> np.ndarray:
        """[n_ue]: UEs with bits queued at the start of ``slot``."""
        self._arrive(slot)
        return self.left > 0

    def take_group(self, first: int, bits: Any) -> None:
        """Slots ``first``, ``first + 1``, ... decoded ``bits`` [slots, n_ue] per UE."""
        for j in range(len(bits)):
            self.take(first + j, bits[j])

    def take(self, slot: int, bits: np.ndarray) -> None:
        """``slot`` decoded ``bits`` per UE: those of the queue are delivered."""
        self._arrive(slot)
        got = self._minimum(bits, self.left)
        self.left -= got
        self.delivered[slot] = got
