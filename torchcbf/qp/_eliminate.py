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
equalities kept. The C kernel applies the same rules to a few problems without gradients
(``torchcbf_dual_solve_small_eq``, :func:`torchcbf.qp.realtime.solve_small`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

#: a row of ``A`` whose distance to the span of the rows before it is at most this fraction of
#: its own norm counts as dependent (the row is then solved with its equalities kept)
RANK_TOL = 1e-7
#: singular values of ``A`` at most this fraction of its largest are zero, to float64
#: rounding, for :func:`numerical_rank`: a float32 ``A`` made of dependent rows is
#: independent to about 1e-8, and is then solved as given (nearly dependent, not dependent)
DEPENDENT_TOL = 1e-12
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


def numerical_rank(A: Tensor) -> tuple[Tensor, Tensor]:
    """``(rank [B], U [B, k, min(k, n)])`` of ``A [B, k, n]``: its singular values above
    :data:`DEPENDENT_TOL` of the largest, and its left singular vectors (largest first)."""
    U, sv, _ = torch.linalg.svd(A, full_matrices=False)
    return (sv > DEPENDENT_TOL * sv[..., :1]).sum(-1), U


def independent_rows(A: Tensor, b: Tensor, U: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(A_r [B, r, n], b_r [B, r], residual [B])`` for ``A [B, k, n]`` of rank ``r`` with
    leading left singular vectors ``U [B, k, r]`` (:func:`numerical_rank`): ``A_r = U'A`` has
    full row rank and ``A = U A_r``, ``b_r = U'b``; ``Ax = b`` holds exactly where
    ``A_r x = b_r`` does if ``b`` lies in the range of ``A``, whose distance is
    ``residual = |b - U b_r|_inf``. Multipliers ``y_r`` of ``A_r x = b_r`` give ``y = U y_r``
    of ``Ax = b``."""
    A_r = U.mT @ A
    b_r = (U.mT @ b.unsqueeze(-1)).squeeze(-1)
    residual = (b - (U @ b_r.unsqueeze(-1)).squeeze(-1)).abs().amax(-1)
    return A_r, b_r, residual


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
