"""A few QPs without gradients, straight from the tensors' memory into proxsuite's dense
solver, verified (and, where small, polished) in numpy.

The objective is scaled first as the torch backend's methods scale it
(:func:`torchcbf.qp._function.data_scaling`: its minimiser does not change, its multipliers
scale back; an answer this route cannot verify goes to the general path), so that
proxsuite's absolute tolerances and the checks mean the same for ``(P, q)`` of any
magnitude.

One mid-size QP (or a handful) costs proxsuite well under a millisecond where it is small;
the general path's tensor operations around it would cost more than the solve. This path
reads the inputs once as float64 arrays, passes ``lb``/``ub`` as proxsuite's box
constraints and rows with ``h = +inf`` not at all, and keeps the answer only where every
row is verified as a KKT point to ``eps`` (the test of
:func:`torchcbf.qp._kkt.kkt_residuals_ok`, here in numpy) and no row's answer is a
direction of unbounded descent; otherwise it returns ``None`` and ``solve_qp`` takes the
general path, which sets every status.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from torchcbf.qp._backends import WATCH_TOL, descends, row_tolerance, solve_watched, unit_rows
from torchcbf.qp._data import QPData
from torchcbf.qp._eliminate import RANK_TOL
from torchcbf.qp._function import ROUTE_EPS, ROUTE_MAX_ITER, data_scaling, saddle_solved
from torchcbf.qp._lu import lu_factor_ex

_BIG = 1e20


def _array(
    t: Tensor | None, shape: tuple[int, ...], trailing: tuple[int, ...]
) -> np.ndarray | None:
    if t is None:
        return None
    B = math.prod(shape)
    return t.detach().expand(*shape, *trailing).reshape(B, *trailing).double().numpy()


def solve_direct(
    Q: Tensor,
    p: Tensor,
    G: Tensor | None,
    h: Tensor | None,
    A: Tensor | None,
    b: Tensor | None,
    lb: Tensor | None,
    ub: Tensor | None,
    eps: float,
    eps_inf: float,
    shape: tuple[int, ...],
) -> tuple[Tensor, ...] | None:
    """``(x, status, lam, nu, iterations, lam_lb, lam_ub, slack)`` with the batch shape
    ``shape`` and ``Q``'s dtype (the fields of :class:`torchcbf.qp.QPSolution`), every row
    solved; ``None`` where some datum is not finite (other than ``h = +inf``, ``lb = -inf``,
    ``ub = +inf``) or some row is not verified (see the module docstring). CPU tensors,
    batch shapes broadcasting to ``shape``."""

    B, n = math.prod(shape), p.shape[-1]
    m = 0 if h is None else h.shape[-1]
    k = 0 if b is None else b.shape[-1]
    P = _array(Q, shape, (n, n))
    P = 0.5 * (P + P.swapaxes(-1, -2))
    q = _array(p, shape, (n,))
    Gn = _array(G, shape, (m, n)) if m else np.zeros((B, 0, n))
    hn = _array(h, shape, (m,)) if m else np.zeros((B, 0))
    An = _array(A, shape, (k, n)) if k else np.zeros((B, 0, n))
    bn = _array(b, shape, (k,)) if k else np.zeros((B, 0))
    lbn = _array(lb, shape, (n,)) if lb is not None else np.full((B, n), -np.inf)
    ubn = _array(ub, shape, (n,)) if ub is not None else np.full((B, n), np.inf)
    finite = all(np.isfinite(v).all() for v in (P, q, Gn, An, bn))
    if not finite or np.isnan(hn).any() or (hn == -np.inf).any():
        return None
    if (
        np.isnan(lbn).any()
        or np.isnan(ubn).any()
        or (lbn == np.inf).any()
        or (ubn == -np.inf).any()
    ):
        return None
    if k and _rank_deficient(An):
        # multipliers free along the dependence of A's rows (1e18 seen) would scale the
        # stationarity test up until a wrong point passes it
        return None
    # the objective scaled as the torch backend's methods scale it (data_scaling)
    c = data_scaling(torch.from_numpy(P), torch.from_numpy(q)).c.numpy()[:, None]
    P, q = P * c[..., None], q * c
    free = hn == np.inf
    lo_box = np.maximum(lbn, -_BIG)
    hi_box = np.minimum(ubn, _BIG)
    # rows of unit length for proxsuite (unit_rows); the answer is verified and polished on
    # the rows as given
    dg, da = unit_rows(Gn), unit_rows(An)
    Gs, hs = Gn * dg[..., None], np.where(free, hn, hn * dg)
    As, bs = An * da[..., None], bn * da
    tolerance = row_tolerance(ROUTE_EPS, dg, da)

    def descending(i: int, d: np.ndarray) -> bool:
        rows = slice(i, i + 1)
        return descends(P[rows], q[rows], Gn[rows], An[rows], lbn[rows], ubn[rows], free[rows],
                        d[None], WATCH_TOL)  # fmt: skip

    for box in (False, True):
        try:
            out = _proxsuite(P, q, Gs, hs, As, bs, lo_box, hi_box, free, box=box,
                             descending=descending, tolerance=tolerance)  # fmt: skip
        except _Descending:
            return None
        if out is None:
            continue
        x, z, zb, y, iters = out
        z, y = z * dg, y * da  # multipliers of the rows as given
        lam = np.maximum(z, 0.0)
        lam_ub = np.where(np.isfinite(ubn), np.maximum(zb, 0.0), 0.0)
        lam_lb = np.where(np.isfinite(lbn), np.maximum(-zb, 0.0), 0.0)
        if _verified(P, q, Gn, hn, An, bn, lbn, ubn, free, x, lam, y, lam_lb, lam_ub, eps):
            break
    else:
        return None
    x, lam, y, lam_lb, lam_ub = _polish(P, q, Gn, hn, An, bn, lbn, ubn, free, x, lam, y,
                                        lam_lb, lam_ub)  # fmt: skip
    if descends(P, q, Gn, An, lbn, ubn, free, x, eps_inf):
        return None
    if _saddle(P, q, Gn, hn, An, bn, lbn, ubn, x, eps):
        return None
    lam, y, lam_lb, lam_ub = lam / c, y / c, lam_lb / c, lam_ub / c  # of (P, q) again
    dtype = Q.dtype

    def out(v: np.ndarray) -> Tensor:
        return torch.from_numpy(v).to(dtype).reshape(*shape, *v.shape[1:])

    status = torch.zeros(shape, dtype=torch.int64)
    return (
        out(x), status, out(lam), out(y), torch.from_numpy(iters).reshape(shape),
        out(lam_lb), out(lam_ub), out(np.zeros((B, m))),
    )  # fmt: skip


def _saddle(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    x: np.ndarray,
    eps: float,
) -> bool:
    """Whether some row's ``x`` is a KKT point but no minimiser (``P`` indefinite: proxsuite
    stops at any KKT point), by :func:`torchcbf.qp._function.saddle_solved` with the bounds
    as rows."""
    try:  # every P positive definite (the test saddle_solved makes): no saddle to look for
        np.linalg.cholesky(P)
        return False
    except np.linalg.LinAlgError:
        pass
    n = P.shape[-1]
    eye = np.broadcast_to(np.eye(n), (P.shape[0], n, n))
    rows = np.concatenate([G, eye, -eye], axis=1)
    bounds = np.concatenate([h, ub, -lb], axis=1)
    data = QPData(*(torch.from_numpy(np.ascontiguousarray(v)) for v in (P, q, rows, bounds, A, b)))
    xt = torch.from_numpy(x)
    return bool(saddle_solved(data, xt, torch.ones(x.shape[0], dtype=torch.bool), eps).any())


def _rank_deficient(A: np.ndarray) -> bool:
    """Whether some row's ``A [k, n]`` is rank deficient: more rows than columns, or a
    singular value within ``RANK_TOL`` of its largest (the tolerance of
    :mod:`torchcbf.qp._eliminate`'s rank rule, which measures each row's distance to the
    span of the rows before it), the rows of ``A`` taken at unit length (independent rows
    of norms 1e8 and 1e-3 are not dependent)."""
    norms = np.linalg.norm(A, axis=-1, keepdims=True)
    sv = np.linalg.svd(A / np.where(norms > 0, norms, 1.0), compute_uv=False)
    return bool((sv[:, -1] <= RANK_TOL * sv[:, 0]).any()) if A.shape[1] <= A.shape[2] else True


class _Descending(Exception):
    """proxsuite's iterates on a row run along a direction of unbounded descent."""


def _proxsuite(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    free: np.ndarray,
    *,
    box: bool,
    descending: Callable[[int, np.ndarray], bool],
    tolerance: np.ndarray,
) -> tuple[np.ndarray, ...] | None:
    """proxsuite's dense solver on every row: ``(x, z, z_bounds, y, iterations)``, or
    ``None`` where some row is not solved. The bounds go in as proxsuite's box (``box``) or
    as identity rows of its double-sided inequalities: the rows are often faster, the box
    more robust (with the rows it has called problems with an optimum infeasible). A row
    whose iterates run along a direction ``d`` with ``descending(i, d)`` raises
    :class:`_Descending` (:func:`~torchcbf.qp._backends.solve_watched`); ``tolerance [B]``:
    each problem's absolute tolerance."""
    from proxsuite import proxqp

    B, n = q.shape
    m, k = h.shape[-1], b.shape[-1]
    x = np.zeros((B, n))
    z = np.zeros((B, m))
    zb = np.zeros((B, n))
    y = np.zeros((B, k))
    iters = np.zeros(B, dtype=np.int64)
    eye = np.eye(n)
    for i in range(B):
        rows = np.flatnonzero(~free[i])
        r = len(rows)
        C, lo_i, hi_i = G[i][rows], np.full(r, -_BIG), h[i][rows]
        if not box:
            C = np.vstack((C, eye))
            lo_i, hi_i = np.concatenate((lo_i, lo[i])), np.concatenate((hi_i, hi[i]))
        qp = proxqp.dense.QP(n, k, len(lo_i), box)
        qp.settings.eps_abs = float(tolerance[i])
        qp.settings.eps_rel = 0.0
        qp.settings.verbose = False
        qp.init(
            P[i], q[i], A[i] if k else None, b[i] if k else None,
            C if len(lo_i) else None, lo_i if len(lo_i) else None, hi_i if len(lo_i) else None,
            *((lo[i], hi[i]) if box else ()),
        )  # fmt: skip
        taken = solve_watched(qp, ROUTE_MAX_ITER, lambda d, i=i: descending(i, d))
        if taken is None:
            raise _Descending
        res = qp.results
        if res.info.status != proxqp.PROXQP_SOLVED:
            return None
        x[i] = res.x
        zr = np.asarray(res.z)
        z[i, rows] = zr[:r]
        zb[i] = zr[r:]
        if k:
            y[i] = res.y
        iters[i] = taken
    return x, z, zb, y, iters


#: largest active-set system (variables, active rows and equalities) the path polishes:
#: beyond it the factorisation would cost more than proxsuite's solve, and the answer stays
#: proxsuite's (accurate to its tolerance, verified to ``eps``)
POLISH_MAX_UNKNOWNS = 200
#: a KKT point "to rounding" (the polish's acceptance test), in units of float64's epsilon
_ROUNDING = 1e4 * np.finfo(np.float64).eps


def _polish(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    free: np.ndarray,
    x: np.ndarray,
    lam: np.ndarray,
    y: np.ndarray,
    lam_lb: np.ndarray,
    lam_ub: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """The answers re-solved on their active sets (rows whose multiplier exceeds their
    slack), kept only where every row's re-solved point is a KKT point to rounding;
    otherwise (and where the system has more than :data:`POLISH_MAX_UNKNOWNS` unknowns) the
    answers as given. The active rows are packed (padded with rows that pin
    their multiplier to zero) and solved with two steps of iterative refinement."""
    B, n = q.shape
    k = b.shape[-1]
    eye = np.broadcast_to(np.eye(n), (B, n, n))
    fin_u, fin_l = np.isfinite(ub), np.isfinite(lb)
    R = np.concatenate(
        (np.where(free[..., None], 0.0, G), eye * fin_u[..., None], -eye * fin_l[..., None]), 1
    )
    r = np.concatenate(
        (np.where(free, 0.0, h), np.where(fin_u, ub, 0.0), np.where(fin_l, -lb, 0.0)), 1
    )
    mult = np.concatenate((lam, lam_ub, lam_lb), 1)
    nonzero = np.abs(R).max(-1) > 0
    active = (mult > r - np.einsum("bmn,bn->bm", R, x)) & nonzero
    counts = active.sum(-1)
    Ka = int(counts.max())
    order = np.argsort(~active, axis=-1, kind="stable")[:, :Ka]
    valid = np.arange(Ka) < counts[:, None]
    Ra = np.take_along_axis(R, order[..., None], 1) * valid[..., None]
    ra = np.where(valid, np.take_along_axis(r, order, 1), 0.0)
    N = n + Ka + k
    if N > POLISH_MAX_UNKNOWNS:
        return x, lam, y, lam_lb, lam_ub
    K = np.zeros((B, N, N))
    K[:, :n, :n] = P
    K[:, :n, n : n + Ka] = Ra.swapaxes(-1, -2)
    K[:, n : n + Ka, :n] = Ra
    K[:, n : n + Ka, n : n + Ka] = np.eye(Ka) * ~valid[:, None, :]
    K[:, :n, n + Ka :] = A.swapaxes(-1, -2)
    K[:, n + Ka :, :n] = A
    rhs = torch.from_numpy(np.concatenate((-q, ra, b), 1)[..., None])
    Kt = torch.from_numpy(K)
    # torch's LU (its thread setting, not numpy's BLAS pool), factored once for the refinement
    LU, pivots, info = lu_factor_ex(Kt)
    if bool((info != 0).any()):
        return x, lam, y, lam_lb, lam_ub
    wt = torch.linalg.lu_solve(LU, pivots, rhs)
    for _ in range(2):
        wt = wt + torch.linalg.lu_solve(LU, pivots, rhs - Kt @ wt)
    w = wt.numpy()
    w = w[..., 0]
    if not np.isfinite(w).all():
        return x, lam, y, lam_lb, lam_ub
    xp, yp = w[:, :n], w[:, n + Ka :]
    mp = np.zeros_like(mult)
    np.put_along_axis(mp, order, np.where(valid, w[:, n : n + Ka], 0.0), 1)
    if not _exact(P, q, R, r, A, b, xp, mp, yp):
        return x, lam, y, lam_lb, lam_ub
    m = lam.shape[-1]
    mp = np.maximum(mp, 0.0)
    return xp, mp[:, :m], yp, mp[:, m + n :], mp[:, m : m + n]


def _exact(
    P: np.ndarray,
    q: np.ndarray,
    R: np.ndarray,
    r: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    x: np.ndarray,
    z: np.ndarray,
    y: np.ndarray,
) -> bool:
    """Whether every row's ``(x, z, y)`` is a KKT point to rounding (the test of
    :func:`torchcbf.qp._kkt.kkt_point`): rows ``Rx <= r``, ``Ax = b`` each judged on
    ``|rhs_i| + max|R_i| (1 + max|x|)``, multipliers nonnegative, no positive multiplier on a
    slack row, stationary component by component."""
    tol = _ROUNDING
    xmax = 1.0 + np.abs(x).max(-1, keepdims=True)
    tiny = np.finfo(np.float64).tiny
    slack = (r - np.einsum("bmn,bn->bm", R, x)) / np.maximum(
        np.abs(r) + np.abs(R).max(-1) * xmax, tiny
    )
    if A.shape[1]:
        eq = np.abs(np.einsum("ben,bn->be", A, x) - b) / np.maximum(
            np.abs(b) + np.abs(A).max(-1) * xmax, tiny
        )
        if eq.max() > tol:
            return False
    zmax = 1.0 + np.abs(z).max(-1, keepdims=True, initial=0.0)
    if (slack < -tol).any() or (z < -tol * zmax).any():
        return False
    if ((z > tol * zmax) & (slack > tol)).any():
        return False
    res = np.einsum("bij,bj->bi", P, x) + q + np.einsum("bmn,bm->bn", R, z)
    res = res + np.einsum("ben,be->bn", A, y)
    scale = (
        np.einsum("bij,bj->bi", np.abs(P), np.abs(x))
        + np.abs(q)
        + np.einsum("bmn,bm->bn", np.abs(R), np.abs(z))
        + np.einsum("ben,be->bn", np.abs(A), np.abs(y))
    )
    scale = scale + tol * scale.max(-1, keepdims=True)
    return bool((np.abs(res) <= tol * np.maximum(scale, tiny)).all())


def _verified(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    free: np.ndarray,
    x: np.ndarray,
    lam: np.ndarray,
    y: np.ndarray,
    lam_lb: np.ndarray,
    lam_ub: np.ndarray,
    eps: float,
) -> bool:
    """Whether every row is a KKT point to ``eps``: rows (``G``, ``A``, bounds) violated by
    at most ``eps`` of ``|rhs_i| + max|R_i| (1 + max|x|)``, stationary to ``eps`` of the
    largest term, duality gap at most ``eps`` of its terms."""
    xmax = 1.0 + np.abs(x).max(-1, keepdims=True)
    hf = np.where(free, 0.0, h)
    gx = np.einsum("bmn,bn->bm", G, x)
    viol = [np.zeros((len(x), 1))]
    if G.shape[1]:
        scale = np.abs(hf) + np.abs(G).max(-1) * xmax
        viol.append(np.where(free, 0.0, np.maximum(gx - hf, 0.0)) / np.maximum(scale, 1e-300))
    if A.shape[1]:
        ax = np.einsum("ben,bn->be", A, x)
        scale = np.abs(b) + np.abs(A).max(-1) * xmax
        viol.append(np.abs(ax - b) / np.maximum(scale, 1e-300))
    lbf, ubf = np.where(np.isfinite(lb), lb, 0.0), np.where(np.isfinite(ub), ub, 0.0)
    viol.append(np.where(np.isfinite(lb), np.maximum(lbf - x, 0.0), 0.0) / (np.abs(lbf) + xmax))
    viol.append(np.where(np.isfinite(ub), np.maximum(x - ubf, 0.0), 0.0) / (np.abs(ubf) + xmax))
    if max(v.max() for v in viol) > eps:
        return False
    terms = (
        np.einsum("bij,bj->bi", P, x),
        q,
        np.einsum("bmn,bm->bn", G, lam),
        np.einsum("ben,be->bn", A, y),
        lam_ub - lam_lb,
    )
    res = np.abs(sum(terms)).max(-1)
    if (res > eps * (1.0 + np.max([np.abs(t).max(-1) for t in terms], axis=0))).any():
        return False
    gap = (
        (lam * (hf - gx)).sum(-1)
        + (y * (b - np.einsum("ben,bn->be", A, x))).sum(-1)
        + (lam_ub * (ubf - x)).sum(-1)
        + (lam_lb * (x - lbf)).sum(-1)
    )
    gap_scale = (
        1.0
        + np.abs((x * terms[0]).sum(-1))
        + np.abs((q * x).sum(-1))
        + np.abs((lam * hf).sum(-1))
        + np.abs((y * b).sum(-1))
        + np.abs((lam_ub * ubf).sum(-1))
        + np.abs((lam_lb * lbf).sum(-1))
    )
    return bool((np.abs(gap) <= eps * gap_scale).all())
