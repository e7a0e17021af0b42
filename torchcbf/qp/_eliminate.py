"""Equality rows eliminated by a null-space basis: ``Ax = b`` turned into ``x = x_p + Z w``.

With ``A' = [Y Z] [R; 0]`` (a complete QR factorisation of ``A' [n, k]``, ``k < n`` rows of full
rank), every ``x`` with ``Ax = b`` is ``x_p + Z w`` for ``x_p = Y R'^{-1} b`` and ``w`` in
``R^(n-k)``, so

    min 1/2 x'Px + q'x  s.t.  Gx <= h, Ax = b

is the inequality-only problem

    min 1/2 w'(Z'PZ)w + (Z'(P x_p + q))'w  s.t.  (GZ) w <= h - G x_p

over ``n - k`` variables, which the dual active-set method (and its C kernel) solves; its
multipliers ``z`` are those of the full problem, and the equality multipliers follow from
stationarity, ``A'y = -(Px + q + G'z)``, i.e. ``y = -R^{-1} Y'(Px + q + G'z)``. ``Z`` has
orthonormal columns, so ``Z'PZ`` is no worse conditioned than ``P``, and the equalities
hold at ``x_p + Z w`` to rounding for every ``w``. A row whose ``A`` is rank deficient or
nearly so (some row of ``A`` within :data:`RANK_TOL` of the span of the rows before it,
relative to its own norm) is not reduced (``ok`` false): its caller solves it with the
equalities kept.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

#: a row of ``A`` whose distance to the span of the rows before it is at most this fraction of
#: its own norm counts as dependent (the row is then solved with its equalities kept)
RANK_TOL = 1e-7
#: a row of ``G`` whose part outside the span of ``A``'s rows is at most this fraction of its
#: own largest entry lies in that span (rounding of the projection, see :func:`reduced_rows`)
SPAN_TOL = 1e-12


class Reduction(NamedTuple):
    """The null-space form of ``Ax = b`` for a batch: ``x = xp + Z w``.

    ``Y [B, n, k]`` and ``Z [B, n, n-k]`` orthonormal bases of the row space of ``A`` and of
    its null space, ``R [B, k, k]`` upper triangular with ``A' = Y R``, ``xp [B, n]`` the
    particular solution, ``ok [B]`` the rows whose ``A`` has full row rank (see
    :data:`RANK_TOL`); on the other rows the other fields are meaningless (and may not be
    finite)."""

    Y: Tensor
    Z: Tensor
    R: Tensor
    xp: Tensor
    ok: Tensor


def reduce_equalities(A: Tensor, b: Tensor) -> Reduction:
    """The :class:`Reduction` of ``A [B, k, n]``, ``b [B, k]`` (``0 < k < n``)."""
    k = A.shape[-2]
    Qf, Rf = torch.linalg.qr(A.mT, mode="complete")
    Y, Z, R = Qf[..., :k], Qf[..., k:], Rf[..., :k, :]
    # NaN or inf in A fails the comparison, so such a row is not ok either
    ok = (R.diagonal(dim1=-2, dim2=-1).abs() > RANK_TOL * A.norm(dim=-1)).all(-1)
    xp = Y @ torch.linalg.solve_triangular(R.mT, b.unsqueeze(-1), upper=False)
    return Reduction(Y, Z, R, xp.squeeze(-1), ok)


def reduced_objective(red: Reduction, P: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """``(Z'PZ, Z'(P xp + q))`` for ``P [B, n, n]`` (symmetric), ``q [B, n]``."""
    Zt = red.Z.mT
    Pr = Zt @ (P @ red.Z)
    qr = Zt @ (P @ red.xp.unsqueeze(-1) + q.unsqueeze(-1))
    return Pr, qr.squeeze(-1)


def reduced_rows(red: Reduction, G: Tensor, h: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """``(GZ, h - G xp)`` for ``G [B, m, n]``, ``h [B, m]``; a row in the span of ``A``'s rows
    (``|G_i Z|`` at most :data:`SPAN_TOL` of ``|G_i|``) becomes exactly zero, with its right-hand
    side rounded up to zero where it is negative by at most ``eps`` of its scale
    (``|h_i| + |G_i| (1 + |xp|)``): such a row is a consequence of the equalities, satisfied or
    contradicted by them outright. Left as the rounding of ``GZ``, it would read as a row of its
    own tiny scale that a huge ``w`` satisfies."""
    Gr = G @ red.Z
    hr = h - (G @ red.xp.unsqueeze(-1)).squeeze(-1)
    g_max = G.abs().amax(-1)
    gone = Gr.abs().amax(-1) <= SPAN_TOL * g_max
    scale = h.abs() + g_max * (1.0 + red.xp.abs().amax(-1, keepdim=True))
    hr = torch.where(gone & (hr >= -eps * scale), hr.clamp_min(0.0), hr)
    return torch.where(gone.unsqueeze(-1), 0.0, Gr), hr


def full_point(red: Reduction, w: Tensor) -> Tensor:
    """``xp + Z w [B, n]`` for ``w [B, n-k]``."""
    return red.xp + (red.Z @ w.unsqueeze(-1)).squeeze(-1)


def equality_multipliers(red: Reduction, grad: Tensor) -> Tensor:
    """``y [B, k]`` with ``A'y = -grad`` for ``grad = Px + q + G'z + ... [B, n]`` (the part of
    ``grad`` outside the row space of ``A`` is zero at a solution of the reduced problem)."""
    rhs = -(red.Y.mT @ grad.unsqueeze(-1))
    return torch.linalg.solve_triangular(red.R, rhs, upper=True).squeeze(-1)


def _mT(a: np.ndarray) -> np.ndarray:
    return a.swapaxes(-1, -2)


def _mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    return (M @ v[..., None])[..., 0]


def solve_small(
    Q: np.ndarray,
    p: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    eps: float,
    inner: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray] | None],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The elimination of this module for a few small problems, in numpy (float64 arrays
    with the same leading dimensions ``[...]``: ``Q [..., n, n]``, ``p [..., n]``,
    ``G [..., m, n]``, ``h [..., m]`` (box bounds as rows, ``h`` finite), ``A [..., k, n]``,
    ``b [..., k]``, ``0 < k < n``): one problem costs a few microseconds of array calls, where
    the batched tensor operations of the functions above would cost several times the solve.
    ``inner(P, q, G, h)`` solves the reduced inequality-only problem and returns
    ``(w, z, iterations)`` or ``None``. Returns ``(x, z, y, iterations)``, or ``None`` where
    some ``A`` is rank deficient (:data:`RANK_TOL`) or ``inner`` gives up. The rules are those
    of :func:`reduce_equalities`, :func:`reduced_rows` and :func:`equality_multipliers`."""
    k = A.shape[-2]
    Qf, Rf = (t.numpy() for t in torch.linalg.qr(torch.from_numpy(_mT(A)), mode="complete"))
    Y, Z, R = Qf[..., :k], Qf[..., k:], Rf[..., :k, :]
    diag = np.diagonal(R, axis1=-2, axis2=-1)
    if not (diag * diag > RANK_TOL**2 * (A * A).sum(-1)).all():
        return None
    R_inv = np.linalg.inv(R)  # k x k, well conditioned by the test above
    xp = _mv(Y, _mv(_mT(R_inv), b))
    P = 0.5 * (Q + _mT(Q))
    Zt = _mT(Z)
    Pr = Zt @ (P @ Z)
    qr = _mv(Zt, _mv(P, xp) + p)
    Gr = G @ Z
    hr = h - _mv(G, xp)
    g_max = np.abs(G).max(-1, initial=0.0)
    gone = np.abs(Gr).max(-1, initial=0.0) <= SPAN_TOL * g_max
    if gone.any():
        scale = np.abs(h) + g_max * (1.0 + np.abs(xp).max(-1, keepdims=True))
        hr = np.where(gone & (hr >= -eps * scale), np.maximum(hr, 0.0), hr)
        Gr = np.where(gone[..., None], 0.0, Gr)
    out = inner(Pr, qr, Gr, hr)
    if out is None:
        return None
    w, z, iters = out
    x = xp + _mv(Z, w)
    grad = _mv(P, x) + p + _mv(_mT(G), z)
    y = -_mv(R_inv, _mv(_mT(Y), grad))
    return x, z, y, iters
