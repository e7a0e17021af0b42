"""Real-time path for a few small QPs on the CPU: numpy arrays straight into the C kernel.

Public for the layers above (the safety filter's real-time path): :func:`available`,
:func:`default_eps`, :func:`solve_rows`, :func:`solve_small` and :data:`MAX_BATCH`.

A control loop solves ONE small QP per tick; there the cost of a solve is the number of
tensor operations around the kernel, not the kernel. :func:`solve_small` takes the data as
float64 numpy arrays (batch first), turns finite box bounds into rows, calls the dual
active-set kernel of :mod:`torchcbf.qp._dual_native` once and returns numpy arrays. It
answers only when the kernel certifies every row (``ok``); otherwise it returns ``None``
and the caller runs the general path, so its answers are exactly the kernel's, which
``solve_qp`` would return for the same rows.
"""

from __future__ import annotations

import ctypes
from typing import NamedTuple

import numpy as np
import torch

from torchcbf.qp import _dual_native
from torchcbf.qp._function import MAX_DUAL_CONDITION, dual_budget
from torchcbf.qp._ipm import default_tolerances

#: largest batch the numpy path takes (beyond it the general path's threads pay off)
MAX_BATCH = 16


def available() -> bool:
    """Whether the C kernel was built and loads (the real-time path needs it)."""
    return _dual_native.available()


def default_eps(dtype: torch.dtype) -> float:
    """``solve_qp``'s default tolerance for inputs of ``dtype``."""
    return default_tolerances(dtype)[0]


class SmallSolution(NamedTuple):
    """The kernel's answer, every field a numpy view with the batch shape ``[...]`` asked for
    (so that ``torch.from_numpy`` converts each at no copy): ``x [..., N]``, multipliers
    ``z [..., m]`` (rows of ``G``), ``z_lb, z_ub [..., N]`` (zeros where a bound is absent),
    ``slack [..., m]`` zeros, ``nu [..., 0]``; int64 ``status [...]`` (zeros: every row
    solved) and ``iterations [...]``."""

    x: np.ndarray
    status: np.ndarray
    z: np.ndarray
    nu: np.ndarray
    iterations: np.ndarray
    z_lb: np.ndarray
    z_ub: np.ndarray
    slack: np.ndarray


def solve_small(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray | None,
    h: np.ndarray | None,
    lb: np.ndarray | None,
    ub: np.ndarray | None,
    eps: float,
    max_iter: int,
    shape: tuple[int, ...],
    dtype: type = np.float64,
) -> SmallSolution | None:
    """Solve ``min 1/2 x'Px + q'x  s.t.  Gx <= h, lb <= x <= ub`` for float64 arrays
    ``P [B,N,N]`` (symmetric), ``q [B,N]``, ``G [B,m,N]``, ``h [B,m]``, ``lb, ub [B,N]``
    (bounds may be infinite; ``lb < +inf`` and ``ub > -inf``); the answer has the batch
    shape ``shape`` (``B`` entries) and the float ``dtype``.

    Returns ``None`` when the kernel does not apply (``N > 64``, no rows), when some datum is
    not finite, or when the kernel does not certify every row; the caller then solves the
    batch by the general path, which also sets those rows' statuses."""
    B, N = q.shape
    if N > _dual_native.MAX_VARS:
        return None
    rows = [] if G is None else [G]
    rhs = [] if h is None else [h]
    m = 0 if h is None else h.shape[1]
    eye = np.eye(N)
    for bound, sign in ((ub, 1.0), (lb, -1.0)):
        if bound is None:
            continue
        finite = np.isfinite(bound)
        rows.append(sign * finite[:, :, None] * eye)
        rhs.append(np.where(finite, sign * bound, 1.0))
    if not rows:
        return None
    Gs = np.concatenate(rows, 1) if len(rows) > 1 else rows[0]
    hs = np.concatenate(rhs, 1) if len(rhs) > 1 else rhs[0]
    out = solve_rows(P, q, Gs, hs, eps, max_iter)
    if out is None:
        return None
    floats, ints = out
    M = hs.shape[1]
    nx, nz = B * N, B * M
    if dtype != np.float64:
        floats = floats.astype(dtype)
    z = floats[nx : nx + nz].reshape(B, M)
    zeros = floats[nx + nz + B * N * N :]
    zero_n = zeros[B * m : B * (m + N)].reshape(*shape, N)
    z_ub = z[:, m : m + N].reshape(*shape, N) if ub is not None else zero_n
    z_lb = z[:, M - N :].reshape(*shape, N) if lb is not None else zero_n
    return SmallSolution(
        floats[:nx].reshape(*shape, N),
        ints[B * (N + 1) :].reshape(shape),
        z[:, :m].reshape(*shape, m),
        zeros[:0].reshape(*shape, 0),
        ints[B * N : B * (N + 1)].reshape(shape),
        z_lb,
        z_ub,
        zeros[: B * m].reshape(*shape, m),
    )


def _diagonally_dominant(P: np.ndarray) -> bool:
    """Whether every Jacobi-scaled ``P`` (unit diagonal) has off-diagonal row sums at most
    1/2: then its eigenvalues lie in [1/2, 3/2] (Gershgorin), its condition is at most 3 and
    the condition estimate of :func:`solve_rows` is not needed."""
    d = 1.0 / np.sqrt(np.abs(np.diagonal(P, axis1=1, axis2=2)))
    S = np.abs(P) * d[:, :, None] * d[:, None, :]
    return bool((S.sum(-1) <= 1.5 + 1e-12).all())


def solve_rows(
    P: np.ndarray, q: np.ndarray, G: np.ndarray, h: np.ndarray, eps: float, max_iter: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Solve ``min 1/2 x'Px + q'x  s.t.  Gx <= h`` (bounds already rows) for float64
    ``P [B,N,N], q [B,N], G [B,M,N], h [B,M]`` in at most ``max_iter`` steps, raised to the
    dual method's budget (:func:`~torchcbf.qp._function.dual_budget`); returns the kernel's
    buffers ``(floats, ints)``: ``floats = [x (B N) | z (B M) | L (B N N) | zeros (B (M + N))]``,
    ``ints = [slots (B N) | iterations (B) | zeros (B)]``. ``None`` when some datum is not
    finite, the kernel does not certify every row, or a row is too ill-conditioned for the
    dual method."""
    B, N = q.shape
    M = h.shape[1]
    if N > _dual_native.MAX_VARS or M < 1:
        return None
    # one input buffer [P | q | G | h] (each batch first), one finiteness test for all
    data = np.concatenate((P.reshape(-1), q.reshape(-1), G.reshape(-1), h.reshape(-1)))
    if not np.isfinite(data.sum()):
        return None
    # outputs: floats [x | z | L | zeros], bytes [active | ok | infeasible],
    # ints [slots | iters | zeros]
    nx, nz, nL = B * N, B * M, B * N * N
    floats = np.zeros(nx + nz + nL + B * M + B * N)
    bytes_ = np.empty(B * (M + 2), dtype=np.uint8)
    ints = np.zeros(B * (N + 2), dtype=np.int64)
    d, f, b8, i8 = (a.ctypes.data for a in (data, floats, bytes_, ints))
    oq = 8 * nL
    oG = oq + 8 * nx
    oh = oG + 8 * B * M * N
    steps = dual_budget(max_iter, M, N)
    code = _dual_native._kernel().torchcbf_dual_forward(
        B, N, M, d, d + oq, d + oG, d + oh, ctypes.c_double(eps), min(steps, 2**31 - 1),
        f, f + 8 * nx, b8, i8, f + 8 * (nx + nz), b8 + B * M, i8 + 8 * nx, b8 + B * (M + 1),
    )  # fmt: skip
    if code != 0:
        raise MemoryError("torchcbf: the QP kernel could not allocate its workspace")
    if not bytes_[B * M : B * (M + 1)].all():
        return None
    if np.count_nonzero(P) > B * N and not _diagonally_dominant(P):
        L = floats[nx + nz : nx + nz + nL].reshape(B, N, N)
        Linv = np.linalg.inv(L)  # numpy's batched inverse: one call, no per-matrix overhead
        cond = ((L * L).sum(-1) * (Linv * Linv).sum(-2)).max(-1)
        if not (cond <= MAX_DUAL_CONDITION).all():
            return None  # the general path re-solves such rows by the interior point method
    return floats, ints
