"""Real-time path for a few small QPs on the CPU: one call of the C kernel.

Public for the layers above (the safety filter's real-time path, whose kernel links the QP
kernel): :func:`available`, :func:`default_eps`, :func:`solve_small`,
:data:`MAX_BATCH`, :data:`MAX_DUAL_CONDITION` and :data:`KERNEL_VERSION`.

A control loop solves ONE small QP per tick; there the cost of a solve is the number of
tensor operations around the kernel, not the kernel. :func:`solve_small` hands the data
(CPU tensors, batch first) to ``torchcbf_dual_solve_small`` of the dual active-set kernel
(:mod:`torchcbf.qp._dual_native`), which turns the finite box bounds into rows, solves,
checks the conditioning and writes the answers into tensors. It answers only when the
kernel certifies every row; otherwise it returns ``None`` and the caller runs the general
path, so its answers are exactly the kernel's, which ``solve_qp`` would return for the same
rows.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._native import check_operands, float64_pointers
from torchcbf.qp import _dual_native, _eliminate
from torchcbf.qp._function import MAX_DUAL_CONDITION, dual_budget
from torchcbf.qp._ipm import default_tolerances

#: largest batch the path takes (beyond it the general path's threads pay off)
MAX_BATCH = 16
#: version of the QP kernel's C source (a library linking it folds it into its own)
KERNEL_VERSION = _dual_native.KERNEL_VERSION
__all__ = [
    "KERNEL_VERSION",
    "MAX_BATCH",
    "MAX_DUAL_CONDITION",
    "SmallSolution",
    "available",
    "default_eps",
    "solve_small",
]


def available() -> bool:
    """Whether the C kernel was built and loads (the real-time path needs it)."""
    return _dual_native.available()


def default_eps(dtype: torch.dtype) -> float:
    """``solve_qp``'s default tolerance for inputs of ``dtype``."""
    return default_tolerances(dtype)[0]


class SmallSolution(NamedTuple):
    """The kernel's answer, every field a tensor with the batch shape ``[...]`` asked for:
    ``x [..., N]``, multipliers ``z [..., m]`` (rows of ``G``), ``nu [..., k]`` (equality
    rows; ``k = 0`` without them),
    ``z_lb, z_ub [..., N]`` (zeros where a bound is absent), ``slack [..., m]`` zeros; int64
    ``status [...]`` (zeros: every row solved) and ``iterations [...]``. The field order is
    that of :class:`torchcbf.qp.QPSolution`."""

    x: Tensor
    status: Tensor
    z: Tensor
    nu: Tensor
    iterations: Tensor
    z_lb: Tensor
    z_ub: Tensor
    slack: Tensor


def solve_small(
    P: Tensor,
    q: Tensor,
    G: Tensor | None,
    h: Tensor | None,
    lb: Tensor | None,
    ub: Tensor | None,
    eps: float,
    max_iter: int,
    shape: tuple[int, ...],
    dtype: torch.dtype = torch.float64,
    *,
    A: Tensor | None = None,
    b: Tensor | None = None,
) -> SmallSolution | None:
    """Solve ``min 1/2 x'Px + q'x  s.t.  Gx <= h, Ax = b, lb <= x <= ub`` for CPU tensors
    ``P [...,N,N]``, ``q [...,N]``, ``G [...,m,N]``, ``h [...,m]``, ``A [...,k,N]``,
    ``b [...,k]`` (``0 < k < N``), ``lb, ub [...,N]`` with the batch shape ``shape`` (``B``
    entries; only their values are read, no gradient flows; ``G, h``, ``A, b`` or bounds
    may be ``None``; bounds may be infinite) in at most ``max_iter`` steps, raised to the
    dual method's budget (:func:`~torchcbf.qp._function.dual_budget`); the answer has the
    batch shape ``shape`` and the float ``dtype``. Equality rows are eliminated in the
    kernel (``x = xp + Z w``, the rules of :mod:`torchcbf.qp._eliminate`), where rows with
    ``h = +inf`` bound nothing.

    Returns ``None`` when the kernel does not apply (``N > 64``, no rows, ``k >= N``), when
    some datum is not finite (or ``lb = +inf``, ``ub = -inf``), when some ``A`` is rank
    deficient, when the kernel does not certify every row, or when some ``P`` is too
    ill-conditioned for the dual method; the caller then solves the batch by the general
    path, which also sets those rows' statuses."""
    B, N = math.prod(shape), q.shape[-1]
    m = 0 if h is None else h.shape[-1]
    k = 0 if b is None else b.shape[-1]
    rows = m + (N if ub is not None else 0) + (N if lb is not None else 0)
    fn = _dual_native.function("torchcbf_dual_solve_small_eq") if k else None
    if N > _dual_native.MAX_VARS or rows < 1 or k >= N or (k and fn is None):
        return None
    check_operands(
        "solve_small",
        [(name, t, (*shape, *trailing)) for name, t, trailing in (
            ("P", P, (N, N)), ("q", q, (N,)), ("G", G, (m, N)), ("h", h, (m,)),
            ("A", A, (k, N)), ("b", b, (k,)), ("lb", lb, (N,)), ("ub", ub, (N,)),
        )],
    )  # fmt: skip
    if (G is None) != (h is None) or (A is None) != (b is None):
        raise ValueError("solve_small: G and h, A and b go together")
    pointers, held = float64_pointers((P, q, G, h, A, b, lb, ub))  # held: alive through the call
    f64 = torch.float64
    x, z, nu = (torch.empty(*shape, c, dtype=f64) for c in (N, m, k))
    z_lb, z_ub = torch.empty(*shape, N, dtype=f64), torch.empty(*shape, N, dtype=f64)
    iters = torch.empty(shape, dtype=torch.int64)
    budget = min(dual_budget(max_iter, rows, N - k), 2**31 - 1)
    if k:
        code = fn(
            B, N, m, k, *pointers, eps, budget, MAX_DUAL_CONDITION, _eliminate.RANK_TOL,
            _eliminate.SPAN_TOL, torch.finfo(dtype).eps, x.data_ptr(), z.data_ptr(),
            nu.data_ptr(), z_lb.data_ptr(), z_ub.data_ptr(), iters.data_ptr(),
        )  # fmt: skip
    else:
        code = _dual_native._kernel().torchcbf_dual_solve_small(
            B, N, m, *pointers[:4], *pointers[6:], eps, budget, MAX_DUAL_CONDITION,
            x.data_ptr(), z.data_ptr(), z_lb.data_ptr(), z_ub.data_ptr(), iters.data_ptr(),
        )  # fmt: skip
    if code < 0:
        raise MemoryError("torchcbf: the QP kernel could not allocate its workspace")
    if code:
        return None
    if dtype != f64:
        x, z, nu, z_lb, z_ub = (v.to(dtype) for v in (x, z, nu, z_lb, z_ub))
    status = torch.zeros_like(iters)
    return SmallSolution(x, status, z, nu, iters, z_lb, z_ub, torch.zeros_like(z))
