"""Control Lyapunov function candidates: ``V(x) >= 0``, zero at the goal."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchcbf._checks import as_tensor, check_spd
from torchcbf.barriers._params import StateIndex
from torchcbf.barriers.lie import AnalyticDerivatives, LieFunction


class Lyapunov(LieFunction):
    """A Lyapunov function candidate as a module: ``forward(x [..., n], t=None) -> V [...]``.

    ``lie`` is the same routine as for barriers (:func:`~torchcbf.barriers.lie_derivatives`):
    ``LieTerms(h=V, lfh=L_f V, lgh=L_g V, dhdt, hess_trace, dhdx)``.
    """


class QuadraticLyapunov(Lyapunov):
    """``V = (p - goal)' P (p - goal)`` with ``p = x[..., index]``.

    Args:
        goal: ``[d]``.
        P: symmetric positive definite ``[d, d]`` (identity by default).
        index: the ``d`` state components (default ``0..d-1``).
        learnable: store ``goal`` and ``P`` as ``nn.Parameter``.
        state_dim: check ``index`` (and the state size) at construction.
    """

    def __init__(
        self,
        goal: Tensor | Sequence[float],
        P: Tensor | None = None,
        index: Sequence[int] | None = None,
        *,
        learnable: bool = False,
        state_dim: int | None = None,
    ) -> None:
        super().__init__()
        g = self.register_constant("goal", goal, learnable=learnable)
        if g.dim() != 1 or g.shape[0] == 0:
            raise ValueError(f"goal must have shape [d], got {tuple(g.shape)}")
        d = g.shape[0]
        if P is None:
            P = torch.eye(d, dtype=g.dtype, device=g.device)
        Pm = self.register_constant("P", P, learnable=learnable)
        if Pm.shape != (d, d):
            raise ValueError(f"P must have shape [{d}, {d}], got {tuple(Pm.shape)}")
        check_spd("P", as_tensor("P", Pm.detach()))
        self._sel = StateIndex(index, d, state_dim)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> V [...]``."""
        e = self._sel(x) - self.goal.to(x)
        return ((e @ self.P.to(x)) * e).sum(-1)

    @property
    def has_analytic(self) -> bool:
        return True

    def derivatives(self, x: Tensor, t: Tensor) -> AnalyticDerivatives:
        e = self._sel(x) - self.goal.to(x)
        P = self.P.to(x)
        Ps = P + P.mT
        V = ((e @ P) * e).sum(-1)
        dhdx = self._sel.scatter(e @ Ps.mT, x.shape[-1])

        def quad(s: Tensor) -> Tensor:
            sp = self._sel.rows(s)
            return (sp * (Ps @ sp)).sum((-2, -1))

        return AnalyticDerivatives(V, dhdx, torch.zeros_like(V), quad)

    def extra_repr(self) -> str:
        return f"index={self._sel.index}"
