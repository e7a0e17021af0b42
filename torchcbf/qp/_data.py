"""``QPData``: one batch of problems in the solvers' standard form, passed between methods."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class QPData(NamedTuple):
    """The batch ``min 1/2 x'Px + q'x  s.t.  Gx <= h, Ax = b``: ``P [B,N,N], q [B,N],
    G [B,M,N], h [B,M], A [B,E,N], b [B,E]`` (box bounds and elastic slacks are already rows
    and variables; ``M`` and ``E`` may be zero)."""

    P: Tensor
    q: Tensor
    G: Tensor
    h: Tensor
    A: Tensor
    b: Tensor

    @property
    def batch(self) -> int:
        """``B``, the number of problems."""
        return self.q.shape[0]

    @property
    def sizes(self) -> tuple[int, int, int]:
        """``(N, M, E)``: variables, inequality rows, equality rows."""
        return self.q.shape[-1], self.G.shape[-2], self.A.shape[-2]

    def rows(self, idx: Tensor) -> QPData:
        """The problems ``idx [R]`` (int64) of the batch."""
        return QPData(*(t.index_select(0, idx) for t in self))

    def slack(self, x: Tensor) -> Tensor:
        """``h - Gx [B, M]`` at ``x [B, N]``."""
        return self.h - torch.einsum("bmn,bn->bm", self.G, x)

    def expand(self, C: int) -> QPData:
        """Every problem repeated ``C`` times in a row (``[B * C, ...]``, problem-major)."""
        B = self.batch

        def rep(t: Tensor) -> Tensor:
            return t.unsqueeze(1).expand(B, C, *t.shape[1:]).reshape(B * C, *t.shape[1:])

        return QPData(*(rep(t) for t in self))

    def to_float64(self) -> QPData:
        """The data detached, in float64 (the solvers' working precision)."""
        return QPData(*(t.detach().to(torch.float64) for t in self))
