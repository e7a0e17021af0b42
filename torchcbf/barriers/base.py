"""The :class:`Barrier` base class: ``h(x[, t]) >= 0`` is the safe set."""

from __future__ import annotations

from torchcbf.barriers.lie import LieFunction


class Barrier(LieFunction):
    """A control barrier function candidate as a module: safe where ``h(x, t) >= 0``.

    Subclasses write ``forward(x [..., n], t=None) -> h [...]`` (or ``[..., k]`` for ``k``
    barriers evaluated at once). ``lie(x, dynamics, t=None, *, method="autograd",
    hessian=True) -> LieTerms(h, lfh, lgh, dhdt, hess_trace, dhdx)`` derives everything a
    CBF condition needs by batched autograd (see :func:`~torchcbf.barriers.lie_derivatives`).
    """
