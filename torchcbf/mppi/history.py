"""Fixed-size, on-device record of the executed states and times a planner was called with.

Specifications (:mod:`torchcbf.mppi.specs`) read it so that a goal reached inside its window
in the past is not revisited.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class History(NamedTuple):
    """Executed states and their global times, per environment.

    Attributes:
        states: ``[B, N, n]`` recorded states (slot order, not necessarily time order).
        times: ``[B, N]`` global time of each slot.
        valid: ``[B, N]`` bool, which slots hold a recorded state.
    """

    states: Tensor
    times: Tensor
    valid: Tensor


class HistoryBuffer:
    """Ring buffer of ``size`` slots per environment, allocated once on the device.

    ``record`` writes at slot ``count % size`` with tensor indexing (no host sync, no
    reallocation as the history grows); when more than ``size`` states were recorded the
    oldest are overwritten (the planner warns where a cost reads them). ``count`` is a 0-d
    int64 tensor on the device.
    """

    def __init__(self, size: int, batch: int, state_dim: int, *, device, dtype) -> None:
        if size < 1:
            raise ValueError(f"history_size must be >= 1, got {size}")
        self.size = int(size)
        self.states = torch.zeros(batch, self.size, state_dim, device=device, dtype=dtype)
        self.times = torch.zeros(batch, self.size, device=device, dtype=dtype)
        self.count = torch.zeros((), device=device, dtype=torch.long)
        self._slots = torch.arange(self.size, device=device)

    def record(self, x: Tensor, t: Tensor) -> None:
        """Append ``x [B, n]`` at times ``t [B]`` (in place)."""
        slot = torch.remainder(self.count, self.size).reshape(1)
        self.states.index_copy_(1, slot, x.unsqueeze(1))
        self.times.index_copy_(1, slot, t.unsqueeze(1))
        self.count.add_(1)

    def view(self) -> History:
        """The recorded history (a view on the buffers: do not modify)."""
        valid = (self._slots < self.count).unsqueeze(0).expand(self.times.shape)
        return History(self.states, self.times, valid)

    def clear(self) -> None:
        """Forget every recorded state."""
        self.count.zero_()
