"""Exact, fixed-cost solver for small strictly convex QPs by active-set enumeration.

For ``min 1/2 x'Px + q'x  s.t.  Gx <= h (M rows), Ax = b (E rows)`` with ``P`` positive
definite, the solution is unique and its KKT multipliers can be chosen supported on a linearly
independent set of rows (conic Caratheodory), i.e. on at most ``N - E`` inequality rows
besides the equalities. This module tries every such candidate set ``S`` at once, for every
row of the batch:

- with ``R = [A; G]``, ``x_u = -P^{-1} q``, ``W = R P^{-1} R'`` and ``r = R x_u - [b; h]``,
  the equality-constrained QP on ``S`` has multipliers ``W_SS mu = r_S`` and solution
  ``x_S = x_u - P^{-1} R_S' mu`` (Schur complement, one Cholesky of ``P`` per row);
- the small ``W_SS`` systems (size ``<= N``, padded with the identity) are solved by an
  unrolled Gaussian elimination whose every step is one tensor operation over
  ``[batch, candidates]``, so the cost is fixed and there is no per-matrix kernel launch;
- a candidate is accepted only as a *verified* KKT point: stationarity holds by construction,
  and primal feasibility (``Gx <= h + tol``), equality and active-row residuals (``|.| <= tol``)
  and dual feasibility (``mu_G >= -tol``) are checked, so an ill-conditioned or singular
  candidate can only be rejected, never accepted wrongly. Among candidates, the one with the
  smallest scaled KKT violation wins (``argmin`` on the device, no host sync).

Rows with no accepted candidate (primal infeasible, ``P`` not positive definite, dependent
equalities, or too ill-conditioned) are reported in ``ok`` and left to the interior point
method by the caller. The number of candidates is
``C = sum_{k <= N - E} binom(M, k)`` (minus sets holding both bounds of one variable, which
are linearly dependent), so the path is meant for small problems; see
:func:`num_candidates`.
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf.qp import _kkt
from torchcbf.qp._data import QPData
from torchcbf.qp._kkt import gradient_size, multiplier_size, row_scale, scaled_violation

#: ``method="auto"`` enumerates when the candidate count is at most ``MAX_CANDIDATES``, or at
#: most ``MAX_CANDIDATES_SMALL_BATCH`` for batches of at most ``SMALL_BATCH`` rows (measured on
#: a 2-core CPU, scripts/bench_qp.py --crossover: at B=1024 enumeration is ~1.6x faster than
#: the interior point method at 163 candidates and ~2.5x slower at 431; at B<=64 it is faster
#: up to 600+, where the interior point method's fixed per-iteration overhead dominates)
MAX_CANDIDATES = 256
MAX_CANDIDATES_SMALL_BATCH = 800
SMALL_BATCH = 64
#: rows x candidates per chunk: keeps the scalar planes of the elimination in cache
_CHUNK_ELEMENTS = 1 << 15


class EnumResult(NamedTuple):
    """``x [B,N]``, ``z [B,M]``, ``y [B,E]``, ``active [B,M]`` bool, ``ok [B]`` bool and
    ``score [B]``, the chosen candidate's scaled KKT violation (``ok`` where at most
    ``eps``; ``inf`` where no candidate was solvable)."""

    x: Tensor
    z: Tensor
    y: Tensor
    active: Tensor
    ok: Tensor
    score: Tensor


@functools.lru_cache(maxsize=256)
def num_candidates(
    M: int, E: int, N: int, pairs: tuple[tuple[int, int], ...] = (), cap: int | None = None
) -> int:
    """Number of candidate active sets for ``M`` inequalities, ``E`` equalities, ``N`` vars;
    with ``cap``, counting stops at the first set size that takes the count beyond it (the
    result is then some number above ``cap``)."""
    kmax = N - E
    if kmax < 0:
        return 0
    # sets with at most one row of each (disjoint) pair: choose j pairs, one side each
    npairs = len(pairs)
    free = M - 2 * npairs
    total = 0
    for k in range(min(kmax, M) + 1):
        total += sum(
            math.comb(npairs, j) * 2**j * math.comb(free, k - j) for j in range(min(k, npairs) + 1)
        )
        if cap is not None and total > cap:
            break
    return total


@functools.lru_cache(maxsize=64)
def _table_cpu(M: int, E: int, N: int, pairs: tuple[tuple[int, int], ...]) -> tuple[Tensor, Tensor]:
    """Candidate table ``T [C, K]`` (indices into ``[A; G]`` rows) and validity ``[C, K]``."""
    kmax = min(N - E, M)
    K = E + kmax
    forbidden = [set(pr) for pr in pairs]
    rows, valid = [], []
    for k in range(kmax + 1):
        for sub in itertools.combinations(range(M), k):
            s = set(sub)
            if any(f <= s for f in forbidden):
                continue
            idx = list(range(E)) + [E + i for i in sub]
            rows.append(idx + [0] * (K - len(idx)))
            valid.append([True] * len(idx) + [False] * (K - len(idx)))
    C = len(rows)
    T = torch.tensor(rows, dtype=torch.int64).reshape(C, K)
    return T, torch.tensor(valid, dtype=torch.bool).reshape(C, K)


@functools.lru_cache(maxsize=64)
def _table(
    M: int, E: int, N: int, pairs: tuple[tuple[int, int], ...], device: torch.device
) -> tuple[Tensor, Tensor]:
    T, valid = _table_cpu(M, E, N, pairs)
    return T.to(device), valid.to(device)


def _eliminate(Wss: Tensor, rs: Tensor, piv_tol: float) -> tuple[Tensor, Tensor]:
    """Solve ``Wss mu = rs`` for symmetric PSD ``Wss [K, K, *batch]`` (batch dims last, so
    every scalar plane ``Wss[i, j]`` is contiguous) by unrolled symmetric Gaussian elimination.

    Returns ``(mu [K, *batch], nonsingular [*batch])``; a pivot below ``piv_tol`` times its
    diagonal (a row nearly dependent on the previous ones) marks the system singular."""
    K = Wss.shape[0]
    if K == 0:
        return rs, torch.ones(Wss.shape[2:], dtype=torch.bool, device=Wss.device)
    a = {(i, j): Wss[i, j] for i in range(K) for j in range(i, K)}
    rhs = list(rs.unbind(0))
    pivots = []
    for j in range(K):
        piv = a[j, j]
        pivots.append(piv)
        inv = torch.reciprocal(piv)
        for i in range(j + 1, K):
            f = a[j, i] * inv
            for k in range(i, K):
                a[i, k] = torch.addcmul(a[i, k], f, a[j, k], value=-1.0)
            rhs[i] = torch.addcmul(rhs[i], f, rhs[j], value=-1.0)
    piv = torch.stack(pivots, 0)
    nonsing = (piv > piv_tol * Wss.diagonal(dim1=0, dim2=1).movedim(-1, 0)).all(0)
    mu: list[Tensor] = [rhs[0]] * K
    for j in range(K - 1, -1, -1):
        acc = rhs[j]
        for i in range(j + 1, K):
            acc = torch.addcmul(acc, a[j, i], mu[i], value=-1.0)
        mu[j] = acc / pivots[j]
    return torch.stack(mu, 0), nonsing


class _Table(NamedTuple):
    T: Tensor  # [C, K] row indices into [A; G] (padding: Rn)
    valid: Tensor  # [C, K]
    flat: Tensor  # [K*K*C] indices into W.reshape(B, Rn*Rn).T extended by rows [1, 0]
    ineq: Tensor  # [K, C, 1] valid inequality entries (float 1/0)
    absmask: Tensor  # [C, Rn] bool, the same rows


@functools.lru_cache(maxsize=64)
def _table(
    M: int, E: int, N: int, pairs: tuple[tuple[int, int], ...], device: torch.device
) -> _Table:
    T, valid = _table_cpu(M, E, N, pairs)
    C, K = T.shape
    Rn = E + M
    flat = T.T.unsqueeze(1) * Rn + T.T.unsqueeze(0)  # [K, K, C]
    pair = valid.T.unsqueeze(1) & valid.T.unsqueeze(0)
    diag = torch.eye(K, dtype=torch.bool).unsqueeze(-1)
    # padded entries read a spare 1 (diagonal) or 0 (off the diagonal)
    flat = torch.where(pair, flat, torch.where(diag, Rn * Rn, Rn * Rn + 1)).reshape(-1)
    ineq = (valid & (T >= E)).T.unsqueeze(-1).double()
    absmask = torch.zeros(C, Rn + 1, dtype=torch.bool)
    absmask.scatter_(1, torch.where(valid, T, Rn), True)
    absmask = absmask[:, :Rn]
    absmask[:, :E] = True
    Tp = torch.where(valid, T, Rn)
    return _Table(*(t.to(device) for t in (Tp, valid, flat, ineq, absmask)))


def _solve_chunk(
    L: Tensor,
    q: Tensor,
    R: Tensor,
    hr: Tensor,
    E: int,
    tab: _Table,
    eps: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Enumerate for one chunk; returns ``(x, mult [B,E+M], chosen-set mask [B,E+M], ok,
    score)``."""
    B, N = q.shape
    Rn = R.shape[-2]
    C, K = tab.T.shape
    dtype = q.dtype
    xu = -torch.cholesky_solve(q.unsqueeze(-1), L).squeeze(-1)
    U = torch.cholesky_solve(R.mT, L)  # P^{-1} R'  [B, N, Rn]
    W = R @ U  # [B, Rn, Rn]
    r = (R @ xu.unsqueeze(-1)).squeeze(-1) - hr  # [B, Rn]

    # candidate systems, batch dimensions last: Wss [K, K, C, B], rs [K, C, B]
    Wt = torch.cat((W.reshape(B, Rn * Rn).T, W.new_ones(1, B), W.new_zeros(1, B)), 0)
    Wss = Wt.index_select(0, tab.flat).view(K, K, C, B)
    rt = torch.cat((r.T, r.new_zeros(1, B)), 0)
    rs = rt[tab.T.T]  # [K, C, B] (padding reads the zero row)
    piv_tol = 1e-12 if dtype == torch.float64 else 1e-6
    mu, nonsing = _eliminate(Wss, rs, piv_tol)  # [K, C, B], [C, B]

    # residuals of every row for every candidate: res = R x_S - [b; h] = r - W[:, S] mu,
    # with a spare zero column that padding entries point to
    mu_full = q.new_zeros(B, C, Rn + 1).scatter_(-1, tab.T.expand(B, C, K), mu.permute(2, 1, 0))
    W_ext = W.new_zeros(B, Rn + 1, Rn + 1)
    W_ext[:, :Rn, :Rn] = W
    r_ext = torch.cat((r, r.new_zeros(B, 1)), -1)
    res = torch.baddbmm(r_ext.unsqueeze(1), mu_full, W_ext, alpha=-1.0)  # [B, C, Rn + 1]
    # each row's residual on that row's own scale (as in the dual method), so a tiny row next
    # to a huge one still counts
    scale = row_scale(R, hr, xu).clamp_min(torch.finfo(dtype).tiny)
    res = res / torch.cat((scale, hr.new_ones(B, 1)), -1).unsqueeze(1)
    # max(res, 0) over every row (the spare column is 0), and |res| on the rows of S
    pviol = torch.maximum(res.amax(-1), res.gather(-1, tab.T.expand(B, C, K)).amin(-1).neg())
    if E > 0:
        pviol = torch.maximum(pviol, res[..., :E].abs().amax(-1))
    # each multiplier judged as its term in the stationarity, against the largest term
    # (:func:`multiplier_size`), so the test does not depend on the units
    w = torch.cat((R.abs().amax(-1).T, R.new_zeros(1, B)), 0)[tab.T.T]  # [K, C, B]
    size = mu * w
    grad = q.abs().amax(-1)
    scale = torch.maximum(grad, size.abs().amax(0)) if K else grad.expand(C, B)
    neg = (size * tab.ineq.to(dtype)).amin(0).neg().clamp_min(0.0)
    dviol = neg / torch.where(scale > 0, scale, 1.0)  # [C, B]
    score = torch.maximum(pviol, dviol.T).nan_to_num_(nan=math.inf)
    score = torch.where(nonsing.T, score, math.inf)
    best_score, best = score.min(-1)
    mult = mu_full[torch.arange(B, device=q.device), best, :Rn]  # [B, Rn]
    chosen = tab.absmask[best] & ~(torch.arange(Rn, device=q.device) < E)
    x = xu - (U @ mult.unsqueeze(-1)).squeeze(-1)
    # stationarity check of the winner (guards against an inaccurate P^{-1})
    Px = (L @ (L.mT @ x.unsqueeze(-1))).squeeze(-1)
    stat = Px + q + (R.mT @ mult.unsqueeze(-1)).squeeze(-1)
    _, dscale = multiplier_size(R, mult, gradient_size(q, Px))
    ok = (best_score <= eps) & (stat.abs().amax(-1) <= eps * dscale)
    ok = ok & torch.isfinite(x).all(-1)
    # the winner's rows on its own scale: the candidates were judged on x_u's, which a weak
    # curvature makes huge enough to pass an O(1) violation
    ok = ok & (scaled_violation(R[:, E:], hr[:, E:], R[:, :E], hr[:, :E], x) <= eps)
    return x, mult, chosen, ok, best_score


def solve_enum(
    data: QPData,
    *,
    eps: float,
    pairs: tuple[tuple[int, int], ...] = (),
) -> EnumResult:
    """Solve a batch by active-set enumeration (see module docstring).

    Shapes: ``P [B,N,N], q [B,N], G [B,M,N], h [B,M], A [B,E,N], b [B,E]`` (finite).
    ``pairs`` lists inequality rows that cannot be active together (both bounds of a
    variable). Returns :class:`EnumResult`; rows with ``ok = False`` hold zeros and must be
    solved by another method. Rows are processed in chunks of bounded memory (a loop over
    blocks of rows, not over rows)."""
    P, q, G, h, A, b = data
    B, N = q.shape
    M, E = G.shape[-2], A.shape[-2]
    if E > N:  # no candidate set (its rows would be dependent): every row is left to the caller
        return EnumResult(
            q.new_zeros(B, N), h.new_zeros(B, M), b.new_zeros(B, E),
            torch.zeros(B, M, dtype=torch.bool, device=q.device),
            torch.zeros(B, dtype=torch.bool, device=q.device), q.new_full((B,), math.inf),
        )  # fmt: skip
    L, info = torch.linalg.cholesky_ex(P)
    pd = info == 0
    L = torch.where(pd.view(B, 1, 1), L, torch.eye(N, dtype=P.dtype, device=P.device))
    tab = _table(M, E, N, pairs, q.device)
    R = torch.cat((A, G), -2)
    hr = torch.cat((b, h), -1)
    C = tab.T.shape[0]
    chunk = max(1, _CHUNK_ELEMENTS // C)
    outs = [
        _solve_chunk(
            L[i : i + chunk], q[i : i + chunk], R[i : i + chunk], hr[i : i + chunk], E, tab, eps
        )
        for i in range(0, B, chunk)
    ]
    if len(outs) == 1:
        x, mult, chosen, ok, score = outs[0]
    else:
        x, mult, chosen, ok, score = (torch.cat(t, 0) for t in zip(*outs, strict=True))
    ok = ok & pd
    okc = ok.unsqueeze(-1)
    x = torch.where(okc, x, 0.0)
    mult = torch.where(okc, mult, 0.0)
    y, z = mult[:, :E], mult[:, E:].clamp_min(0.0)
    active = chosen[:, E:] & okc
    return EnumResult(x, z, y, active, ok, score)


def solve_enum_kkt(
    data: QPData,
    *,
    eps: float,
    pairs: tuple[tuple[int, int], ...] = (),
) -> EnumResult:
    """Enumeration on each candidate's own KKT system (:func:`torchcbf.qp._kkt.solve_active`,
    batched over rows and candidates), without ``P^{-1}``: for a few rows whose ``P`` is too
    ill-conditioned for :func:`solve_enum`, whose Schur complement works around
    ``x_u = -P^{-1} q`` and loses the digits a weak curvature costs (``x_u ~ 1e8`` for a
    ``P`` of condition 1e9). Each candidate is judged on its own point (rows on their own
    scale, multipliers against their largest); the best one within ``eps`` is kept (``ok``),
    and where ``P`` is not positive definite (a saddle is a KKT point too) the one of least
    objective among those within ``eps``.
    Its cost is about ``B C`` small LU factorisations for ``C`` candidates: meant for the
    few rows the Schur complement loses (the caller solves them in blocks)."""
    P, q, G, h, A, b = data
    B, N = q.shape
    M, E = G.shape[-2], A.shape[-2]
    tab = _table(M, E, N, pairs, q.device)
    C = tab.absmask.shape[0]

    act = tab.absmask[:, E:].unsqueeze(0).expand(B, C, M).reshape(B * C, M)
    each = data.expand(C)
    x, z, y, solved = _kkt.solve_active(each, act)
    pviol = scaled_violation(each.G, each.h, each.A, each.b, x)
    grad = gradient_size(each.q, (each.P @ x.unsqueeze(-1)).squeeze(-1))
    zs, zscale = multiplier_size(each.G, z, grad)
    dviol = (-zs.amin(-1)).clamp_min(0.0) / zscale if M > 0 else x.new_zeros(B * C)
    score = torch.where(solved, torch.maximum(pviol, dviol), math.inf).view(B, C)
    score = score.nan_to_num(nan=math.inf)
    best_score, best = score.min(-1)
    # where P is not positive definite a KKT point may be a saddle: of the candidates within
    # eps, one of least objective (the minimiser, where one exists, is among them); objectives
    # within eps of the least tie (nearly parallel rows give candidates a rounding apart, the
    # lower one slightly infeasible), and of those the one with the smallest violation wins
    indefinite = torch.linalg.cholesky_ex(P).info != 0
    objective = ((0.5 * (each.P @ x.unsqueeze(-1)).squeeze(-1) + each.q) * x).sum(-1)
    valid = (score <= eps) & torch.isfinite(objective.view(B, C))
    objective = torch.where(valid, objective.view(B, C), math.inf)
    lowest = objective.amin(-1, keepdim=True)
    tied = valid & (objective <= lowest + eps * (1.0 + lowest.abs()))
    least = torch.where(tied, score, math.inf).argmin(-1)
    take = indefinite & valid.any(-1)
    best = torch.where(take, least, best)
    best_score = torch.where(take, score.gather(-1, least.unsqueeze(-1)).squeeze(-1), best_score)
    pick = (torch.arange(B, device=q.device) * C + best).view(B)
    x, z, y, active = x[pick], z[pick].clamp_min(0.0), y[pick], act[pick]
    ok = best_score <= eps
    okc = ok.unsqueeze(-1)
    return EnumResult(
        torch.where(okc, x, 0.0), torch.where(okc, z, 0.0), torch.where(okc, y, 0.0),
        active & okc, ok, best_score,
    )  # fmt: skip
