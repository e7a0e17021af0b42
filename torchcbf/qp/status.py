"""Per-row solver status codes shared by every QP backend."""

from __future__ import annotations

from enum import IntEnum


class Status(IntEnum):
    """Outcome of one QP in a batch (``QPSolution.status`` holds these as int64).

    - ``SOLVED``: primal/dual residuals and duality gap below tolerance.
    - ``PRIMAL_INFEASIBLE``: a Farkas certificate ``y >= 0, G'y + A'nu = 0, h'y + b'nu < 0``
      (box rows included) was found; ``x`` is zero-filled.
    - ``DUAL_INFEASIBLE``: an unbounded descent direction ``d`` (``Qd = 0, Ad = 0, Gd <= 0,
      p'd < 0``) was found; ``x`` is zero-filled.
    - ``MAX_ITER``: the iteration budget ran out first; ``x`` is the last iterate (finite:
      clamped to the dtype's range).
    - ``NON_FINITE``: the row's data held NaN/inf (other than infinite box bounds); ``x`` is zero.
    - ``NUMERICAL_ERROR``: a factorisation broke down (e.g. an indefinite ``Q``), or the
      interior point's answer could not be verified as a KKT point to tolerance by any exact
      re-solve; ``x`` is the last finite iterate.
    """

    SOLVED = 0
    PRIMAL_INFEASIBLE = 1
    DUAL_INFEASIBLE = 2
    MAX_ITER = 3
    NON_FINITE = 4
    NUMERICAL_ERROR = 5
