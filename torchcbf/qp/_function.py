"""The differentiable QP map ``(P, q, G, h, A, b) -> (x, z, y)`` as a ``torch.autograd.Function``.

The forward dispatches to a backend, always works in float64 internally (the barrier's
normal equations lose every digit in float32 close to the solution) and returns outputs in the
input dtype. The backward is the implicit differentiation of the active-set KKT conditions
(:mod:`torchcbf.qp._kkt`), shared by every differentiable backend.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch._C import _functions

from torchcbf._autograd import refuse_transforms
from torchcbf._checks import per_row
from torchcbf.qp import _dual_native, _kkt
from torchcbf.qp import _eliminate as eliminate
from torchcbf.qp._data import QPData
from torchcbf.qp._dual import DualFactor, DualResult, NativeFactor, dual_adjoints, solve_dual
from torchcbf.qp._enum import (
    MAX_CANDIDATES_SMALL_BATCH,
    EnumResult,
    num_candidates,
    solve_enum,
    solve_enum_kkt,
)
from torchcbf.qp._ipm import not_positive_definite, solve_ipm, unbounded_rows
from torchcbf.qp.status import Status

#: largest condition estimate ``max_i P_ii (P^{-1})_ii`` (see :func:`condition_estimate`)
#: for which the dual active-set method's answer is kept: it starts at the unconstrained
#: minimiser ``-P^{-1} q``, whose rounding grows with the condition, and its per-row residual
#: checks scale with ``|x|``; beyond this bound a row is re-solved by the interior point
#: method (whose answer the polish verifies). The estimate ignores a diagonal scaling of
#: ``P`` (e.g. control weights of different units), which the method handles
MAX_DUAL_CONDITION = 1e4
#: weight of the proximal term of :func:`_certify_ill_conditioned`, relative to ``P``'s largest
#: diagonal entry, and the most proximal steps it takes
PROX_WEIGHT = 1e-5
PROX_STEPS = 2
#: most candidate KKT systems (rows times candidate sets) :func:`_certified_enum` solves in
#: one block for the rows enumeration by Schur complement could not certify
#: (:func:`solve_enum_kkt`)
KKT_ENUM_SYSTEMS = 4096
#: largest number of variables (after softening) the dual active-set method is used for by
#: its torch implementation (its unrolled eliminations grow as N^3 tensor operations); the C
#: kernel takes up to ``_dual_native.MAX_VARS`` (see :func:`dual_applies`)
MAX_ACTIVE_SET_VARS = 8
#: farthest a polished point no exact method certifies may lie from the interior point's
#: own point, in units of ``sqrt(eps)`` relative to ``1 + max|x|`` (the interior point is
#: accurate to about ``sqrt(eps)`` near nearly parallel active rows)
POLISH_MOVE = 10.0


def dual_budget(max_iter: int, rows: int, n: int) -> int:
    """Steps the dual active-set method may take: ``max_iter``, raised to ``4 (rows + n)``.
    The method ends in finitely many steps (no active set repeats), about one per row that
    joins or leaves, so a smaller budget would only hand solvable rows to another method."""
    return max(max_iter, 4 * (rows + n))


def dual_applies(n: int, kernel: bool) -> bool:
    """Whether the dual active-set method serves ``n`` variables: up to
    :data:`MAX_ACTIVE_SET_VARS` anywhere, up to ``_dual_native.MAX_VARS`` through the C
    kernel (float64 data on the CPU with the kernel built)."""
    return n <= MAX_ACTIVE_SET_VARS or (kernel and n <= _dual_native.MAX_VARS)


class MixedFactor(NamedTuple):
    """The backward's factors of a batch solved by the dual method where some rows need the
    KKT system: the dual method's factors (``ok`` false on those rows) and the active-set KKT
    factor of the rows ``rows [R]``."""

    dual: DualFactor | NativeFactor
    rows: Tensor
    kkt: _kkt.KKTFactor


#: what the forward leaves for the backward
BackwardFactor = _kkt.KKTFactor | DualFactor | NativeFactor | MixedFactor


#: the algorithms that answer a row, in the order of their codes in ``Forward.method`` (and
#: :attr:`torchcbf.qp.QPSolution.method`): the projection formula, the dual active-set
#: method, active-set enumeration, the interior point method (with its polish and exact
#: re-solves), proxsuite's dense solver, a ``qpsolvers`` solver
#: ``"none"``: a row decided before any method ran (non-finite data, ``lb = +inf``, ``h = -inf``)
ANSWERED_BY = (
    "closed_form", "active_set", "enumerate", "ipm", "proxsuite", "qpsolvers", "none"
)  # fmt: skip


def method_code(name: str) -> int:
    """The code of ``name`` (one of :data:`ANSWERED_BY`)."""
    return ANSWERED_BY.index(name)


@dataclass(frozen=True)
class SolverConfig:
    """Options forwarded from ``solve_qp`` to the forward pass."""

    #: the entry of :data:`SOLVERS` that solves the batch
    method: str
    #: ``"torch"``, ``"proxsuite"`` or ``"qpsolvers:<solver>"`` (the ``"outside"`` method)
    backend: str
    eps: float
    eps_inf: float
    max_iter: int
    check_every: int
    polish: bool
    #: the entry of :data:`SOLVERS` for the rows ``"eliminate"`` cannot reduce (``A`` rank
    #: deficient); where it is ``"auto_proxsuite"``, the rows an exact method leaves go to
    #: proxsuite before the interior point method
    fallback: str = "ipm"
    pairs: tuple[tuple[int, int], ...] = ()
    need_factor: bool = True
    #: unit roundoff of the inputs' dtype (the solve itself runs in float64): eigenvalues of
    #: ``P`` below ``n`` of these, relative to the largest, are rounding of a zero
    rounding: float = torch.finfo(torch.float64).eps


class Forward(NamedTuple):
    """What a method of :data:`SOLVERS` returns, float64, ``[B, ...]``: the answer, the
    per-row status, iterations and :data:`ANSWERED_BY` code, and the backward's factor
    (``None`` unless ``cfg.need_factor``)."""

    x: Tensor
    z: Tensor
    y: Tensor
    status: Tensor
    iterations: Tensor
    method: Tensor
    factor: BackwardFactor | None


def _codes(B: int, name: str, device: torch.device) -> Tensor:
    return torch.full((B,), method_code(name), dtype=torch.int64, device=device)


def _closed_form(data: QPData) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
    """Exact solution for one inequality and ``P`` positive definite (projection formula).

    ``x = x_u - lam P^{-1} g`` with ``x_u = -P^{-1} q`` and
    ``lam = max(0, (g'x_u - h) / g'P^{-1}g)``.
    Returns ``None`` when some row's ``P`` is not positive definite (one host sync)."""
    P, q, G, h = data.P, data.q, data.G, data.h
    L, info = torch.linalg.cholesky_ex(P)
    if bool((info != 0).any()):
        return None
    g = G[:, 0, :]
    rhs = torch.stack((-q, g), -1)
    sol = torch.cholesky_solve(rhs, L)
    xu, Pg = sol[..., 0], sol[..., 1]
    gPg = (g * Pg).sum(-1)
    viol = (g * xu).sum(-1) - h[:, 0]
    degenerate = gPg <= 0
    lam = torch.where(
        (viol > 0) & ~degenerate, viol / torch.where(degenerate, 1.0, gPg), torch.zeros_like(viol)
    )
    x = xu - lam.unsqueeze(-1) * Pg
    status = torch.where(
        degenerate & (viol > 0),
        int(Status.PRIMAL_INFEASIBLE),
        torch.full_like(lam, int(Status.SOLVED), dtype=torch.int64),
    )
    x = torch.where((status == int(Status.SOLVED)).unsqueeze(-1), x, torch.zeros_like(x))
    z = lam.unsqueeze(-1)
    s = data.slack(x).clamp_min(0.0)
    return x, s, z, status, torch.zeros_like(status)


def _forward(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """Solve in float64 by the method ``cfg.method`` names (:data:`SOLVERS`)."""
    return SOLVERS[cfg.method](data, cfg, x0)


def _forward_closed_form(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """The projection formula (one inequality row); the interior point method where some
    ``P`` is not positive definite."""
    res = _closed_form(data)
    if res is None:
        return _forward_ipm(data, cfg, x0)
    x, s, z, status, iters = res
    # _closed_form answers only where every P is positive definite: no curvature to follow
    x, z, status = _drop_unbounded(data, x, (z,), status, cfg, convex=True)
    y = data.q.new_zeros(data.batch, data.b.shape[-1])
    fac = _factor(data, x, z > s, status) if cfg.need_factor else None
    return Forward(x, z, y, status, iters, _codes(data.batch, "closed_form", x.device), fac)


def _forward_ipm(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """The interior point method and its polish for every row."""
    x, z, y, status, iters, active, codes = _ipm(data, cfg, x0)
    fac = _factor(data, x, active, status) if cfg.need_factor else None
    return Forward(x, z, y, status, iters, codes, fac)


def _forward_routed(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """proxsuite's dense solver, then the interior point method (:func:`_ipm_routed`)."""
    x, z, y, status, iters, active, codes = _ipm_routed(data, cfg, x0)
    fac = _factor(data, x, active, status) if cfg.need_factor else None
    return Forward(x, z, y, status, iters, codes, fac)


def _forward_outside(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """An outside solver (``cfg.backend``: proxsuite or a ``qpsolvers`` solver) for every
    row, its answer polished and judged as the interior point method's is (:func:`_finish`).
    A row it calls infeasible is solved again by the interior point method, whose answer
    the row takes where that is a certified solution (proxsuite calls about 0.2% of small
    strictly feasible problems primal infeasible)."""
    from torchcbf.qp import _backends

    if cfg.backend == "proxsuite":
        out = _backends.solve_proxsuite(data, eps=cfg.eps, max_iter=cfg.max_iter, x0=x0, gap=True)
        name = "proxsuite"
    else:
        solver = cfg.backend.split(":", 1)[1]
        out = _backends.solve_qpsolvers(solver, data, eps=cfg.eps, max_iter=cfg.max_iter)
        name = "qpsolvers"
    x, s, z, y, status, iters = (t.to(data.q.device) for t in out)
    x, z, y, status, active = _finish(data, x, s, z, y, status, cfg)
    codes = _codes(data.batch, name, x.device)
    claimed = (status == int(Status.PRIMAL_INFEASIBLE)) | (status == int(Status.DUAL_INFEASIBLE))
    if bool(claimed.any()):
        idx = claimed.nonzero().squeeze(-1)
        own = _ipm(data.rows(idx), replace(cfg, backend="torch", method="ipm"), None)
        take = own[3] == int(Status.SOLVED)
        x, z, y, status, iters, active, codes = (
            t.index_copy(0, idx, torch.where(per_row(take, t), o.to(t.dtype), t[idx]))
            for t, o in zip((x, z, y, status, iters, active, codes), own, strict=True)
        )
    fac = _factor(data, x, active, status) if cfg.need_factor else None
    return Forward(x, z, y, status, iters, codes, fac)


def _forward_eliminated(
    data: QPData, cfg: SolverConfig, x0: Tensor | None, *, dependent: bool = True
) -> Forward:
    """Equality rows eliminated (:mod:`torchcbf.qp._eliminate`) and the reduced problem
    solved by the dual active-set method (its rows it cannot certify by the interior point
    method, as in :func:`_forward_dual`). A row whose ``A`` is rank deficient but whose
    ``b`` lies in its range (to ``eps``) is solved on an independent set of its equalities
    (:func:`_forward_dependent`, where ``dependent``); the rows left (an inconsistent ``A``,
    or a reduced Hessian singular to the inputs' rounding of ``P``) are solved with their
    equalities kept, by ``cfg.fallback``. The backward factor is the active-set KKT system
    of the full problem. Finding those rows is one host synchronisation."""
    P, q, G, h, A, b = data
    B, N = q.shape
    k = b.shape[-1]
    base = replace(cfg, method=cfg.fallback, need_factor=False)
    if k >= N:  # no null space to reduce to: independent sets where they are consistent
        every = torch.ones(B, dtype=torch.bool, device=q.device)
        out = _forward_dependent(data, base, x0, every) if dependent else _forward(data, base, x0)
        return _with_factor(data, cfg, *out[:6])
    red = eliminate.reduce_equalities(A, b)
    Pr, qr = eliminate.reduced_objective(red, P, q)
    # a reduced Hessian singular to the inputs' rounding of P: the dual method would answer
    # far along a direction of unbounded descent, so such rows keep their equalities
    full_rank = red.ok
    red = red._replace(ok=red.ok & ~singular_to_rounding(Pr, P, cfg.rounding))
    all_ok = bool(red.ok.all())
    idx = None if all_ok else red.ok.nonzero().squeeze(-1)

    def rows(t: Tensor) -> Tensor:
        return t if idx is None else t.index_select(0, idx)

    Pk, qk, Gk, hk, Pr, qr = (rows(t) for t in (P, q, G, h, Pr, qr))
    red_k = eliminate.Reduction(*(rows(t) for t in red))
    Gr, hr = eliminate.reduced_rows(red_k, Gk, hk, cfg.eps)
    w0 = None
    if x0 is not None:
        w0 = (red_k.Z.mT @ (rows(x0) - red_k.xp).unsqueeze(-1)).squeeze(-1)
    inner = replace(base, method="active_set")
    none = q.new_zeros(Pr.shape[0], 0, N - k)
    w, zk, _, st, it, codes_k, _ = _forward_dual(
        QPData(Pr, qr, Gr, hr, none, none[..., 0]), inner, w0
    )
    xk = eliminate.full_point(red_k, w)
    grad = torch.einsum("bij,bj->bi", Pk, xk) + qk + torch.einsum("bmn,bm->bn", Gk, zk)
    yk = eliminate.equality_multipliers(red_k, grad)
    infeasible = (st == int(Status.PRIMAL_INFEASIBLE)) | (st == int(Status.DUAL_INFEASIBLE))
    xk, zk, yk = (torch.where(infeasible.unsqueeze(-1), 0.0, t) for t in (xk, zk, yk))
    if idx is None:
        x, z, y, status, iters, codes = xk, zk, yk, st, it, codes_k
    else:
        bad = (~red.ok).nonzero().squeeze(-1)
        x0b = None if x0 is None else x0.index_select(0, bad)
        sub = data.rows(bad)
        if dependent:
            out = _forward_dependent(sub, base, x0b, ~full_rank.index_select(0, bad))
        else:
            out = _forward(sub, base, x0b)[:6]
        x, z, y, status, iters, codes = (
            t.new_zeros(B, *t.shape[1:]).index_copy(0, idx, tk).index_copy(0, bad, tb)
            for t, tk, tb in zip(
                (q, h, b, st, it, codes_k), (xk, zk, yk, st, it, codes_k), out, strict=True
            )
        )
    return _with_factor(data, cfg, x, z, y, status, iters, codes)


def _with_factor(
    data: QPData,
    cfg: SolverConfig,
    x: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    iterations: Tensor,
    method: Tensor,
) -> Forward:
    """The :class:`Forward` of an answer, with the active-set KKT factor of the full problem
    where ``cfg`` asks for one."""
    fac = _factor(data, x, _kkt.active_set(z, data.slack(x)), status) if cfg.need_factor else None
    return Forward(x, z, y, status, iterations, method, fac)


def _forward_dependent(
    data: QPData, cfg: SolverConfig, x0: Tensor | None, deficient: Tensor
) -> tuple[Tensor, ...]:
    """``(x, z, y, status, iterations, method)`` of rows that :func:`_forward_eliminated`
    could not reduce. A ``deficient [B]`` row (``A`` rank deficient, also to float64
    rounding: :func:`torchcbf.qp._eliminate.numerical_rank`) whose ``b`` lies in the
    range of ``A`` to ``eps (1 + |b|)``, both judged with every row of ``A`` and ``b``
    divided by the row's norm, is solved, by elimination, on the independent
    equalities ``U'A x = U'b`` (:func:`torchcbf.qp._eliminate.independent_rows`; one pass per
    rank present), its multipliers mapped back (``y = U y_r``): dependent rows leave the KKT
    systems of the other methods singular. Every other row is solved by ``cfg.method`` with its
    equalities kept."""
    # judged on unit rows: a row scaled by 1e12 would otherwise set the scale of both the
    # rank and the consistency of the others (x1 = 0 beside 1e12 x1 = 1e12 held "consistent")
    norm = data.A.norm(dim=-1)
    norm = torch.where(norm > 0, norm, torch.ones_like(norm))
    A_unit, b_unit = data.A / norm.unsqueeze(-1), data.b / norm
    rank, U_all = eliminate.numerical_rank(A_unit)
    deficient = deficient & (rank < data.A.shape[-2])
    left = torch.ones_like(deficient)
    pieces: list[tuple[Tensor, tuple[Tensor, ...]]] = []
    for r in torch.unique(rank[deficient]).tolist():
        if r == 0 or r >= data.q.shape[-1]:  # a single feasible point: solved as given
            continue
        group = (deficient & (rank == r)).nonzero().squeeze(-1)
        sub = data.rows(group)
        U = U_all.index_select(0, group)[..., :r]
        A_g, b_g = A_unit.index_select(0, group), b_unit.index_select(0, group)
        A_r, b_r, residual = eliminate.independent_rows(A_g, b_g, U)
        consistent = residual <= cfg.eps * (1.0 + b_g.abs().amax(-1))
        if not bool(consistent.any()):
            continue
        group, U = group[consistent], U[consistent]
        sub = QPData(*(t[consistent] for t in sub[:4]), A_r[consistent], b_r[consistent])
        x0g = None if x0 is None else x0.index_select(0, group)
        x, z, y_r, st, it, codes = _forward_eliminated(sub, cfg, x0g, dependent=False)[:6]
        # y of the unit rows, U y_r, divided by each row's norm: A'y = A_unit' (U y_r)
        y = (U @ y_r.unsqueeze(-1)).squeeze(-1) / norm.index_select(0, group)
        pieces.append((group, (x, z, y, st, it, codes)))
        left[group] = False
    if bool(left.any()):
        idx = left.nonzero().squeeze(-1)
        x0l = None if x0 is None else x0.index_select(0, idx)
        pieces.append((idx, tuple(_forward(data.rows(idx), cfg, x0l)[:6])))
    out = [v.new_zeros(data.batch, *v.shape[1:]) for v in pieces[0][1]]
    for group, values in pieces:
        out = [t.index_copy(0, group, v) for t, v in zip(out, values, strict=True)]
    return tuple(out)


def _factor(data: QPData, x: Tensor, active: Tensor, status: Tensor) -> _kkt.KKTFactor:
    """The backward's KKT factor: on ``active`` plus every row tight at ``x``."""
    G = data.G
    backward_set = _kkt.with_tight_rows(G, data.h, x, active, status)
    return _kkt.backward_factor(data.P, G, data.A, active, backward_set)


#: absolute tolerance and iteration budget of proxsuite's dense solver where ``auto`` routes
#: rows to it (its own defaults are 1e-5 and 10,000); its answer is then judged to ``eps``
ROUTE_EPS = 1e-9
ROUTE_MAX_ITER = 10_000
#: tolerance of the interior point method on the rows proxsuite leaves (at most the
#: caller's ``eps``): the problems proxsuite fails on are the degenerate ones, where a point
#: converged to ``eps`` in the norm can still miss a small row by more
ROUTE_FALLBACK_EPS = 1e-9

#: one return of :func:`_ipm` and :func:`_ipm_routed`: ``(x, z, y, status, iterations,
#: active, method)``
_IPMOut = tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]


def _ipm_routed(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> _IPMOut:
    """proxsuite's dense solver, then the interior point method for the rows it leaves.

    A row is kept where proxsuite calls it solved, its answer is a KKT point to ``eps``
    (:func:`torchcbf.qp._kkt.kkt_residuals_ok`) and no certificate of unboundedness
    (:func:`unbounded_solved`: ``P`` singular to the inputs' rounding); a kept row is
    polished on its active set (:func:`_polish_active`). Every other row, proxsuite's
    infeasibility claims included, goes to the interior point method, whose certificates set
    the status. Returns what :func:`_ipm` returns."""
    from torchcbf.qp import _backends

    out = _backends.solve_proxsuite(
        data, eps=ROUTE_EPS, max_iter=ROUTE_MAX_ITER, x0=x0, box=True, watch=True
    )
    x, s, z, y, st, iters = (t.to(data.q.device) for t in out)
    ok = (st == int(Status.SOLVED)) & _kkt.kkt_residuals_ok(data, x, z, y, cfg.eps)
    # a minimiser far along a direction where P is singular to the inputs' rounding
    ok = ok & ~unbounded_solved(data, x, ok, cfg)
    status = torch.where(ok, int(Status.SOLVED), int(Status.MAX_ITER))
    active = _kkt.active_set(z, s) & ok.unsqueeze(-1)
    codes = _codes(data.batch, "proxsuite", x.device)
    if cfg.polish and bool(ok.any()):
        x, z, y, active = _polish_active(data, x, z, y, active, ok)
    if bool(ok.all()):
        return x, z, y, status, iters, active, codes
    idx = (~ok).nonzero().squeeze(-1)
    sub = data.rows(idx)
    x0s = None if x0 is None else x0.index_select(0, idx)
    tight = replace(cfg, eps=min(cfg.eps, ROUTE_FALLBACK_EPS))
    xs, zs, ys, sts, its, acts, cs = _ipm(sub, tight, x0s)
    # the interior point method ran to a tighter tolerance than asked for: a row it did not
    # finish whose last point is a KKT point to the caller's eps is solved by that standard
    unfinished = (sts == int(Status.MAX_ITER)) | (sts == int(Status.NUMERICAL_ERROR))
    if bool(unfinished.any()):
        good = unfinished & _kkt.kkt_residuals_ok(sub, xs, zs, ys, cfg.eps)
        good = good & ~unbounded_solved(sub, xs, good, cfg)
        sts = torch.where(good, int(Status.SOLVED), sts)
        acts = torch.where(good.unsqueeze(-1), acts | _kkt.active_set(zs, sub.slack(xs)), acts)
        left = unfinished & ~good
        if cfg.eps > tight.eps and bool(left.any()):
            # a run stalled short of the tighter tolerance can end farther off than a run to
            # the caller's: those rows are solved again to the caller's eps
            jdx = left.nonzero().squeeze(-1)
            again = _ipm(sub.rows(jdx), cfg, None if x0s is None else x0s.index_select(0, jdx))
            again = (*again[:4], again[4] + its.index_select(0, jdx), *again[5:])
            xs, zs, ys, sts, its, acts, cs = (
                t.index_copy(0, jdx, u)
                for t, u in zip((xs, zs, ys, sts, its, acts, cs), again, strict=True)
            )
    return (
        x.index_copy(0, idx, xs),
        z.index_copy(0, idx, zs),
        y.index_copy(0, idx, ys),
        status.index_copy(0, idx, sts),
        iters.index_copy(0, idx, its),
        active.index_copy(0, idx, acts),
        codes.index_copy(0, idx, cs),
    )


def _polish_active(
    data: QPData,
    x: Tensor,
    z: Tensor,
    y: Tensor,
    active: Tensor,
    ok: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(x, z, y, active)`` with the ``ok`` rows' answers replaced by the solution of their
    active-set KKT system where that is a KKT point to rounding
    (:func:`torchcbf.qp._kkt.kkt_point`); elsewhere the answers stay as given.

    The system holds only the active rows (:func:`torchcbf.qp._kkt.solve_active`): an outside
    solver's answer is polished for a fraction of its cost."""
    xp, zp, ya, solved = _kkt.solve_active(data, active, _kkt.POLISH_REFINE_STEPS)
    exact = ok & solved & _kkt.kkt_point(data, xp, zp, ya)
    keep = exact.unsqueeze(-1)
    return (
        torch.where(keep, xp, x),
        torch.where(keep, zp.clamp_min(0.0), z),
        torch.where(keep, ya, y),
        active,
    )


def _ipm(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> _IPMOut:
    """The interior point method and its polish: ``(x, z, y, status, iterations, active,
    method)``."""
    out = solve_ipm(
        data,
        eps=cfg.eps,
        eps_inf=cfg.eps_inf,
        max_iter=cfg.max_iter,
        check_every=cfg.check_every,
        x0=x0,
    )
    x, z, y, status, active = _finish(data, *out[:5], cfg)
    return x, z, y, status, out.iterations, active, _codes(data.batch, "ipm", x.device)


def _finish(
    data: QPData,
    x: Tensor,
    s: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    cfg: SolverConfig,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Polish (or not) an iterative answer; returns ``(x, z, y, status, active)``.

    Nearly parallel active rows leave the interior point accurate only to about
    ``sqrt(eps)`` in ``x``, and an active-set guess missing one of them can still pass the
    polish's ``eps`` checks. So a row the solver calls solved whose polished point is not a
    KKT point to rounding (``exact`` of :func:`torchcbf.qp._kkt.polish`), and a row left
    ``NUMERICAL_ERROR`` or ``MAX_ITER``, is re-solved exactly by the dual active-set method
    (no equality rows), then by enumeration (few candidate sets) where one applies (a row
    without any constraint by a Cholesky solve). A row the solver called solved that
    nothing verifies is reported ``NUMERICAL_ERROR``; a ``MAX_ITER``/``NUMERICAL_ERROR`` row
    keeps its status, or becomes ``DUAL_INFEASIBLE`` (``x``, ``z``, ``y`` zeroed) where its
    ``P`` is singular and its last point is a descent direction. Testing whether any row
    needs this is one host synchronisation. Last, a ``SOLVED`` row whose answer certifies
    unboundedness (:func:`unbounded_solved`) becomes ``DUAL_INFEASIBLE``."""
    if not cfg.polish:
        candidate = (status == int(Status.SOLVED)).unsqueeze(-1)
        active = _kkt.active_set(z, s) & candidate
    else:
        x, z, y, status, active = _polish_and_resolve(data, x, s, z, y, status, cfg)
    x, z, y, active, status = _drop_unbounded(data, x, (z, y, active), status, cfg)
    return x, z, y, status, active


def _polish_and_resolve(
    data: QPData,
    x: Tensor,
    s: Tensor,
    z: Tensor,
    y: Tensor,
    status: Tensor,
    cfg: SolverConfig,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The polish and exact re-solves of :func:`_finish`.

    A polished point that passes the ``eps`` checks but that no exact method certifies is
    kept only near the interior point's own point (within :data:`POLISH_MOVE` ``sqrt(eps)``,
    relative): nearly dependent rows let a wrong active-set guess pass those checks far
    away. Farther off, the row keeps the interior point's answer where that converged, and
    is ``NUMERICAL_ERROR`` otherwise. A polished point that is a saddle
    (:func:`saddle_solved`) counts as not converged. A row the polish cannot verify at all is
    ``NUMERICAL_ERROR``, except where no exact method applies (:func:`_exact_applies`): there
    it keeps the interior point's answer where that converged and is a KKT point to ``eps``
    on the given data (:func:`torchcbf.qp._kkt.kkt_residuals_ok`)."""
    P, q, G, h, A, b = data
    own = (x, s, z, y, status)
    x, z, y, status, polished_active, verified, exact = _kkt.polish(
        data, x, s, z, y, status, eps=cfg.eps
    )
    # a saddle is no answer: the row is re-solved like one the method gave up on
    saddle = saddle_solved(data, x, status == int(Status.SOLVED), cfg.eps)
    status = torch.where(saddle, int(Status.NUMERICAL_ERROR), status)
    solved = status == int(Status.SOLVED)
    failed = (status == int(Status.NUMERICAL_ERROR)) | (status == int(Status.MAX_ITER))
    suspect = (solved & ~exact) | failed
    if not bool(suspect.any()):
        return x, z, y, status, polished_active
    idx = suspect.nonzero().squeeze(-1)
    sub = data.rows(idx)
    xs, zs, ys, acts, ok = _exact_resolve(sub, cfg, failed.index_select(0, idx))
    active = polished_active
    if bool(ok.any()):
        keep = ok.unsqueeze(-1)
        x = x.index_copy(0, idx, torch.where(keep, xs, x.index_select(0, idx)))
        z = z.index_copy(0, idx, torch.where(keep, zs, z.index_select(0, idx)))
        y = y.index_copy(0, idx, torch.where(keep, ys, y.index_select(0, idx)))
        active = active.index_copy(0, idx, torch.where(keep, acts, active.index_select(0, idx)))
    before = status.index_select(0, idx)
    unverified = ~ok & ~verified.index_select(0, idx) & (before == int(Status.SOLVED))
    x_own, s_own, z_own, y_own, status_own = (t.index_select(0, idx) for t in own)
    moved = (x.index_select(0, idx) - x_own).abs().amax(-1)
    far = (
        ~ok
        & ~unverified
        & (before == int(Status.SOLVED))
        & (moved > POLISH_MOVE * cfg.eps**0.5 * (1.0 + x_own.abs().amax(-1)))
    )
    own_solved = status_own == int(Status.SOLVED)
    # beyond the exact methods' reach, a row the polish could not verify keeps the interior
    # point's own answer where that is a KKT point to eps on the caller's data (the method
    # stops on its scaled data); within it, their verdict stands
    own_kkt = unverified & own_solved & (not _exact_applies(data, cfg))
    if bool(own_kkt.any()):
        own_kkt = own_kkt & _kkt.kkt_residuals_ok(sub, x_own, z_own, y_own, cfg.eps)
    revert = (far & own_solved) | own_kkt
    if bool(revert.any()):
        back = revert.unsqueeze(-1)
        x, z, y = (
            t.index_copy(0, idx, torch.where(back, t_own, t.index_select(0, idx)))
            for t, t_own in ((x, x_own), (z, z_own), (y, y_own))
        )
        own_active = _kkt.active_set(z_own, s_own)
        active = active.index_copy(
            0, idx, torch.where(back, own_active, active.index_select(0, idx))
        )
    after = torch.where((unverified | far) & ~revert, int(Status.NUMERICAL_ERROR), before)
    after = torch.where(ok, int(Status.SOLVED), after)
    status = status.index_copy(0, idx, after)
    # a row the interior point gave up on may have run off along a descent direction
    unbounded = ~ok & failed.index_select(0, idx)
    if bool(unbounded.any()):
        unbounded = unbounded & unbounded_rows(
            sub.P, sub.q, sub.G, sub.A, x.index_select(0, idx), cfg.eps_inf
        )
        status = status.index_copy(
            0, idx, torch.where(unbounded, int(Status.DUAL_INFEASIBLE), after)
        )
        drop = torch.zeros_like(status, dtype=torch.bool).index_copy(0, idx, unbounded)
        x, z, y = (torch.where(drop.unsqueeze(-1), 0.0, t) for t in (x, z, y))
        active = active & ~drop.unsqueeze(-1)
    return x, z, y, status, active


def _exact_applies(data: QPData, cfg: SolverConfig) -> bool:
    """Whether :func:`_exact_resolve` has an exact method for these rows (the dual method
    without equality rows, or enumeration of few candidate sets)."""
    N, M, E = data.sizes
    q = data.q
    if M == 0 and E == 0:
        return True
    if E == 0 and dual_applies(N, _dual_native.applies(q)):
        return True
    cap = MAX_CANDIDATES_SMALL_BATCH
    return num_candidates(M, E, N, cfg.pairs, cap=cap) <= cap


def singular_to_rounding(M: Tensor, P: Tensor, rounding: float) -> Tensor:
    """Rows ``[B]`` whose symmetric ``M [B, r, r]`` is not positive definite by more than
    the rounding of ``P [B, n, n]`` (``M - tau I``, ``tau = 2 n rounding max_i sum_j
    |P_ij|``, has no Cholesky factor): ``M`` is ``P`` itself or its reduction ``Z'PZ``."""
    tau = rounding_scale(P, rounding)
    return not_positive_definite(M - torch.diag_embed(tau.unsqueeze(-1).expand(-1, M.shape[-1])))


def rounding_scale(P: Tensor, rounding: float) -> Tensor:
    """``tau [B] = 2 n rounding max_i sum_j |P_ij|``: an eigenvalue of ``P [B, n, n]`` (or of
    a reduction of it) within ``tau`` of zero is zero to ``rounding``."""
    return 2.0 * P.shape[-1] * rounding * P.abs().sum(-1).amax(-1)


def unbounded_solved(data: QPData, x: Tensor, solved: Tensor, cfg: SolverConfig) -> Tensor:
    """Rows ``[B]`` among ``solved`` whose ``x`` certifies that the problem is unbounded
    (:func:`~torchcbf.qp._ipm.unbounded_rows`, ``P`` singular to the inputs' rounding).

    A singular ``P`` rounded to a tiny positive eigenvalue turns a descent direction into a
    minimiser far along it (``|x| ~ 1e11``), which the tolerances of every method accept as a
    KKT point; the point itself is then the certificate. Rounded to a tiny negative
    eigenvalue, it turns the descent direction into a stationary point far along the other
    way (``q'x > 0``, a maximum along ``x``), and ``-x`` is the certificate. On a problem with
    an optimum no point passes (``d``, ``2d``, ... would all be feasible directions with a
    falling objective). The test (an eigendecomposition) runs on the rows with ``q'x != 0``
    whose ``P`` is singular to rounding, after one host synchronisation."""
    P, q = data.P, data.q
    qx = (q * x).sum(-1)
    cand = solved & (qx != 0)
    if not bool(cand.any()):
        return cand
    x = torch.where((qx > 0).unsqueeze(-1), -x, x)  # the way the objective falls
    # P - tau I positive definite, for tau at least the test's singularity threshold
    # (n units of rounding of the largest eigenvalue, bounded by the largest row sum), rules
    # the row out without an eigendecomposition
    cand = cand & singular_to_rounding(P, P, cfg.rounding)
    if not bool(cand.any()):
        return cand
    idx = cand.nonzero().squeeze(-1)
    sub = [t.index_select(0, idx) for t in (P, q, data.G, data.A, x)]
    found = unbounded_rows(*sub, cfg.eps_inf, cfg.rounding)
    return torch.zeros_like(cand).index_copy(0, idx, found)


def saddle_solved(data: QPData, x: Tensor, solved: Tensor, eps: float) -> Tensor:
    """Rows ``[B]`` among ``solved`` whose ``x`` is a stationary point but no minimiser: ``P``
    is not positive definite, and along a direction of negative curvature in the null space
    of the rows tight at ``x`` (equality rows included) the objective falls, inside the
    feasible set, by more than ``eps (1 + |f(x)|)``.

    For a convex problem every KKT point is a minimiser; where ``P`` is indefinite (float32
    rounding of a singular ``P`` is enough) a KKT point can be a saddle far out, with the
    minimiser elsewhere. Each eigenvector ``d`` of the reduced Hessian with an eigenvalue
    ``mu`` below the rounding of ``P`` is followed both ways to the first row it would
    cross: ``f(x + t d) - f(x) = t g'd + mu t^2 / 2``, ``g = P x + q``, is least at that end
    (a ray without such a row is unbounded descent). The test (an SVD and an
    eigendecomposition) runs only on rows whose ``P`` has no Cholesky factor, after one host
    synchronisation."""
    worst, f, _ = _curvature_worst(data, x, solved, eps)
    return worst > eps * (1.0 + f.abs())


def curvature_ray(data: QPData, x: Tensor, solved: Tensor, eps: float) -> Tensor:
    """Rows ``[B]`` among ``solved`` where, from ``x``, a direction of firmly negative
    curvature of ``P`` (as :func:`saddle_solved` follows them, below ``-eps^(1/3)`` of
    ``P``'s scale) stays feasible for ever: the objective has no lower bound (a certificate
    of unboundedness where ``P`` is indefinite)."""
    return _curvature_worst(data, x, solved, eps)[2]


def _curvature_worst(
    data: QPData, x: Tensor, solved: Tensor, eps: float
) -> tuple[Tensor, Tensor, Tensor]:
    """``(fall, f, ray)``, each ``[B]``: the largest fall of the objective from ``x`` along a
    direction of negative curvature (``inf`` along a way that crosses no row), the
    objective at ``x`` and whether such a way certifies unboundedness
    (:func:`_curvature_fall`), on the ``solved`` rows whose ``P`` is not positive definite
    (0 and False elsewhere); one host synchronisation."""
    P, q, G, h, A, b = data
    cand = solved & not_positive_definite(P)
    zero = torch.zeros_like(x[..., 0])
    if not bool(cand.any()):
        return zero, zero, torch.zeros_like(zero, dtype=torch.bool)
    idx = cand.nonzero().squeeze(-1)
    P, q, G, h, A = (t.index_select(0, idx) for t in (P, q, G, h, A))
    x = x.index_select(0, idx)
    Gx = G @ x.unsqueeze(-1)
    slack = h - Gx.squeeze(-1)
    tight = slack <= eps * (1.0 + Gx.squeeze(-1).abs())
    g = (P @ x.unsqueeze(-1)).squeeze(-1) + q
    f = 0.5 * (x * (g + q)).sum(-1)
    worst = torch.zeros_like(f)
    # first in the null space of every tight row; then in that of the equality rows alone,
    # leaving the tight rows inwards (a tight row whose multiplier is zero does not hold a
    # minimiser on its face: at a corner of the box every direction may be blocked by one)
    ray = torch.zeros_like(worst, dtype=torch.bool)
    for inwards in (False, True):
        fall, open_ray = _curvature_fall(P, G, A, g, slack, tight, inwards)
        worst, ray = torch.maximum(worst, fall), ray | open_ray
    nothing = torch.zeros_like(zero, dtype=torch.bool)
    return (zero.index_copy(0, idx, worst), zero.index_copy(0, idx, f),
            nothing.index_copy(0, idx, ray))  # fmt: skip


def _curvature_fall(
    P: Tensor, G: Tensor, A: Tensor, g: Tensor, slack: Tensor, tight: Tensor, inwards: bool
) -> tuple[Tensor, Tensor]:
    """The largest fall of the objective ``[b]`` along a direction of negative curvature of
    ``P`` (an eigenvector of ``P`` reduced to the null space of ``A`` and, unless
    ``inwards``, of the ``tight`` rows), followed either way to the first row it crosses;
    with ``inwards``, a way that leaves a tight row outwards is blocked. ``g``: the
    gradient ``P x + q`` at the point, ``slack [b, M]`` of its rows. Also ``[b]`` bool:
    whether such a way crosses no row along a curvature below ``-eps^(1/3)`` of ``P``'s
    scale (a certificate of unboundedness; a curvature between that and the rounding is
    taken for a rounded singular ``P``)."""
    n = P.shape[-1]
    C = A if inwards else torch.cat([A, G * tight.unsqueeze(-1)], dim=-2)
    eye = torch.eye(n, dtype=P.dtype, device=P.device)
    if C.shape[-2] > 0:
        _, sv, Vh = torch.linalg.svd(C, full_matrices=False)
        keep = sv > 1e-9 * sv.amax(-1, keepdim=True).clamp_min(torch.finfo(P.dtype).tiny)
        V = Vh.mT * keep.unsqueeze(-2)
        Z = eye - V @ V.mT  # projector on the null space of the rows
    else:
        Z = eye.expand_as(P)
    mu, D = torch.linalg.eigh(Z @ (0.5 * (P + P.mT)) @ Z)
    tau = rounding_scale(P, torch.finfo(P.dtype).eps).unsqueeze(-1)
    neg = mu < -tau  # [b, n]: directions (columns of D) of negative curvature
    firm = mu < -rounding_scale(P, torch.finfo(P.dtype).eps ** (1 / 3)).unsqueeze(-1)
    gd = (g.unsqueeze(-1) * D).sum(-2)  # [b, n]
    Gd = G @ D  # [b, M, n]
    free = ~tight.unsqueeze(-1) & torch.isfinite(slack).unsqueeze(-1)
    worst = torch.zeros_like(g[..., 0])
    ray = torch.zeros_like(worst, dtype=torch.bool)
    # a row the direction meets at a rounding of its own norm (|d| = 1) does not stop it
    scale = G.norm(dim=-1, keepdim=True)
    for sign in (1.0, -1.0):
        rate = sign * Gd
        moving = rate > 1e-12 * scale
        crosses = free & moving
        ratio = torch.where(crosses, slack.clamp_min(0.0).unsqueeze(-1) / rate, torch.inf)
        t = ratio.amin(-2) if G.shape[-2] else torch.full_like(gd, torch.inf)  # inf: no row
        fall = torch.where(torch.isinf(t), torch.inf, -(sign * t * gd + 0.5 * mu * t * t))
        usable = neg
        if inwards:
            usable = usable & ~(tight.unsqueeze(-1) & moving).any(-2)
        worst = torch.maximum(worst, torch.where(usable, fall, 0.0).amax(-1))
        # a certificate also leaves no tight row outwards (one the null space kept only to
        # its rank tolerance, a nearly dependent pair, may close the way)
        leaves = (tight.unsqueeze(-1) & moving).any(-2)
        ray = ray | (usable & firm & torch.isinf(t) & ~leaves).any(-1)
    return worst, ray


def _drop_unbounded(
    data: QPData,
    x: Tensor,
    others: tuple[Tensor, ...],
    status: Tensor,
    cfg: SolverConfig,
    *,
    convex: bool = False,
) -> tuple[Tensor, ...]:
    """``(x, *others, status)`` with the rows whose ``x`` :func:`unbounded_solved` or
    :func:`curvature_ray` finds a certificate of unboundedness reported ``DUAL_INFEASIBLE``
    and ``x`` and ``others`` (multipliers, active sets) zeroed there: ``SOLVED`` rows, and rows left
    ``NUMERICAL_ERROR`` or ``MAX_ITER`` (a method stopped on a saddle far out, rejected as an
    answer, ends there; the certificate holds whichever way ``x`` was found)."""
    unfinished = (status == int(Status.NUMERICAL_ERROR)) | (status == int(Status.MAX_ITER))
    rows = (status == int(Status.SOLVED)) | unfinished
    unb = unbounded_solved(data, x, rows, cfg)
    if not convex:  # ``convex``: every P known positive definite
        unb = unb | curvature_ray(data, x, rows, cfg.eps)
    if not bool(unb.any()):
        return (x, *others, status)
    u = unb.unsqueeze(-1)
    out = [torch.where(u, torch.zeros_like(t), t) for t in (x, *others)]
    return (*out, torch.where(unb, int(Status.DUAL_INFEASIBLE), status))


def _exact_resolve(
    data: QPData,
    cfg: SolverConfig,
    strict: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``(x, z, y, active, ok)`` of the exact methods, tried in turn on the rows the ones
    before did not certify: a Cholesky solve without rows, the dual active-set method (no
    equality rows), enumeration (few candidate sets; after the dual method only on the
    ``strict`` rows). On the ``strict [B]`` rows (those the interior point could not solve)
    an answer must also be a KKT point to rounding:
    enumeration judges its choice to ``eps``, which a nearly dependent active set can pass,
    and both methods accept, to ``eps``, data that rounding made slightly infeasible."""
    P, q, G, h, A, b = data
    B, M, E, N = q.shape[0], G.shape[-2], A.shape[-2], q.shape[-1]
    x, z, y = q.new_zeros(B, N), q.new_zeros(B, M), q.new_zeros(B, E)
    active = torch.zeros(B, M, dtype=torch.bool, device=q.device)
    ok = torch.zeros(B, dtype=torch.bool, device=q.device)
    if M == 0 and E == 0:
        L, info = torch.linalg.cholesky_ex(P)
        xs = torch.cholesky_solve(-q.unsqueeze(-1), L).squeeze(-1)
        ok = (info == 0) & torch.isfinite(xs).all(-1) & _kkt.kkt_point(data, xs, z, y)
        return torch.where(ok.unsqueeze(-1), xs, x), z, y, active, ok
    second = strict  # rows enumeration may take after the dual method
    if E == 0 and dual_applies(N, _dual_native.applies(q)):
        dual = solve_dual(P, q, G, h, eps=cfg.eps, max_iter=dual_budget(cfg.max_iter, M, N))
        x, z, active = dual.x, dual.z, dual.active
        ok = dual.ok & (~strict | _kkt.kkt_point(data, x, z, y))
    else:
        second = torch.ones_like(strict)
    second = second & ~ok
    if (
        bool(second.any())
        and num_candidates(M, E, N, cfg.pairs, cap=MAX_CANDIDATES_SMALL_BATCH)
        <= MAX_CANDIDATES_SMALL_BATCH
    ):
        # the same certified enumeration (polished on its active set where the direct solve
        # is a little off) that takes the failed rows before the interior point method, so
        # that a row's status does not depend on how many rows failed beside it
        en = _certified_enum(data, cfg)
        take = en.ok & second
        keep = take.unsqueeze(-1)
        x, z, y = torch.where(keep, en.x, x), torch.where(keep, en.z, z), torch.where(keep, en.y, y)
        active = torch.where(keep, en.active, active)
        ok = ok | take
    return x, z, y, active, ok


def _certified_enum(data: QPData, cfg: SolverConfig) -> EnumResult:
    """Enumeration's answer, kept (``ok``) only where it is a KKT point to rounding, directly
    or once polished on its active set (:func:`_certify`). Rows the Schur complement loses
    (``P`` too ill-conditioned, a far minimiser: a best candidate within rounding of
    ``eps``, or none solvable, yet no certified answer) are enumerated again on each
    candidate's own KKT system (:func:`solve_enum_kkt`), in blocks of rows however many
    there are, so that a row's answer does not depend on how many others failed; rows no
    candidate comes near (infeasible ones) are left to the interior point method, whose
    answer carries the certificate."""
    en = _certify(data, solve_enum(data, eps=cfg.eps, pairs=cfg.pairs), cfg)
    lost = ~en.ok & ((en.score <= cfg.eps**0.5) | ~torch.isfinite(en.score))
    if not bool(lost.any()):
        return en
    N, M, E = data.sizes
    block = max(1, KKT_ENUM_SYSTEMS // max(num_candidates(M, E, N, cfg.pairs), 1))
    for idx in lost.nonzero().squeeze(-1).split(block):
        sub = data.rows(idx)
        ek = _certify(sub, solve_enum_kkt(sub, eps=cfg.eps, pairs=cfg.pairs), cfg)
        en = EnumResult(*(t.index_copy(0, idx, u) for t, u in zip(en, ek, strict=True)))
    return en


def _certify(data: QPData, en: EnumResult, cfg: SolverConfig) -> EnumResult:
    """``en`` with ``ok`` only where its point is a KKT point to rounding, directly or once
    polished on its active set (an ill-conditioned ``P`` leaves the direct solve a little
    off): enumeration judges its choice to ``eps``, which a nearly dependent active set can
    pass with ``x`` far off. A point far along a descent direction (``P`` singular to
    rounding) is no answer: the row goes to the interior point method, whose result carries
    the certificate."""
    unbounded = unbounded_solved(data, en.x, en.ok, cfg) | curvature_ray(data, en.x, en.ok, cfg.eps)
    en = en._replace(ok=en.ok & ~unbounded)
    exact = en.ok & _kkt.kkt_point(data, en.x, en.z, en.y)
    redo = en.ok & ~exact
    if not bool(redo.any()):
        return en._replace(ok=exact)
    idx = redo.nonzero().squeeze(-1)
    sub = data.rows(idx)
    x, z, y = (t.index_select(0, idx) for t in (en.x, en.z, en.y))
    slack = sub.slack(x).clamp_min(0.0)
    solved = torch.full_like(idx, int(Status.SOLVED))
    xe, ze, ye, _, act_e, _, polished = _kkt.polish(sub, x, slack, z, y, solved, eps=cfg.eps)
    keep = polished.unsqueeze(-1)
    return en._replace(
        x=en.x.index_copy(0, idx, torch.where(keep, xe, x)),
        z=en.z.index_copy(0, idx, torch.where(keep, ze, z)),
        y=en.y.index_copy(0, idx, torch.where(keep, ye, y)),
        active=en.active.index_copy(
            0, idx, torch.where(keep, act_e, en.active.index_select(0, idx))
        ),
        ok=exact.index_copy(0, idx, polished),
    )


def _forward_enum(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """Active-set enumeration for every row; the rows it cannot certify (infeasible, ``P``
    not positive definite, too ill-conditioned, or no KKT point to rounding after the
    polish, :func:`_certified_enum`) go to the interior point method."""
    en = _certified_enum(data, cfg)
    iters = torch.zeros(data.batch, dtype=torch.int64, device=data.q.device)
    codes = _codes(data.batch, "enumerate", data.q.device)
    x, z, y, status, iters, active, codes = _ipm_fallback(
        data, cfg, x0, en.x, en.z, en.y, en.active, en.ok, iters, codes
    )
    fac = _factor(data, x, active, status) if cfg.need_factor else None
    return Forward(x, z, y, status, iters, codes, fac)


def condition_estimate(L: Tensor, batch_first: bool = True) -> Tensor:
    """``max_i P_ii (P^{-1})_ii [B]`` from the Cholesky factor ``L`` of ``P = L L'``
    (``[B, N, N]``, or ``[N, N, B]``): a lower bound of the condition number of the
    Jacobi-scaled ``D^{-1/2} P D^{-1/2}`` (``D = diag(P)``), 1 for a diagonal ``P``.

    ``(P^{-1})_ii`` is the squared norm of column ``i`` of ``L^{-1}``, whose rows follow by
    forward substitution, one ``[B, N]`` operation per entry of ``L`` (no per-matrix call)."""
    if not batch_first:
        L = L.permute(2, 0, 1)
    N = L.shape[-1]
    rows: list[Tensor] = []  # rows of L^{-1}, each [B, N]
    eye = torch.eye(N, dtype=L.dtype, device=L.device)
    for i in range(N):
        acc = eye[i].expand(L.shape[0], N)
        for k in range(i):
            acc = acc - L[:, i, k : k + 1] * rows[k]
        rows.append(acc / L[:, i, i : i + 1])
    inv_diag = sum(r * r for r in rows)  # [B, N]
    p_diag = (L * L).sum(-1)  # P_ii = |row i of L|^2
    return (p_diag * inv_diag).amax(-1)


def _forward_dual(data: QPData, cfg: SolverConfig, x0: Tensor | None) -> Forward:
    """Dual active-set method for every row (no equality rows); the rows it cannot certify go
    to the interior point method. The backward uses the dual method's own factors when every
    row was solved by it and no row has a tight row outside its active set (a degenerate
    vertex, where the method's multipliers may leave out a row that must stay tight); the
    other rows get the active-set KKT factorisation, row by row (:class:`MixedFactor`).
    Finding them is a second host synchronisation, with gradients only."""
    P, q, G, h, A, b = data
    y = q.new_zeros(q.shape[0], 0)
    steps = dual_budget(cfg.max_iter, G.shape[-2], q.shape[-1])
    res = solve_dual(P, q, G, h, eps=cfg.eps, max_iter=steps, check_every=cfg.check_every)
    native = isinstance(res.factor, NativeFactor)
    if native:  # the same rule in the kernel, without a pass of tensor operations
        ok = _dual_native.well_conditioned(res.factor.L, res.ok, MAX_DUAL_CONDITION)
    elif res.factor.condition is not None:  # the Triton kernel's, from its own factor
        ok = res.ok & (res.factor.condition <= MAX_DUAL_CONDITION)
    else:
        ok = res.ok & (condition_estimate(res.factor.L, batch_first=False) <= MAX_DUAL_CONDITION)
    x, z, rescued = _certify_ill_conditioned(data, res, ok, cfg)
    codes = _codes(data.batch, "active_set", x.device)
    x, z, y, status, iters, active, codes = _ipm_fallback(
        data, cfg, x0, x, z, y, res.active, ok if rescued is None else ok | rescued,
        res.iterations, codes, infeasible=res.infeasible, none_fail=rescued is None,
    )  # fmt: skip
    if not cfg.need_factor:
        return Forward(x, z, y, status, iters, codes, None)
    if native:
        solved = status == int(Status.SOLVED)
        backward_set = _dual_native.tight_rows(G, h, x, active, solved, _kkt.TIGHT)
    else:
        backward_set = _kkt.with_tight_rows(G, h, x, active, status)
    # rows another method solved, and rows with tight rows outside the dual active set;
    # rows not SOLVED get zero gradients from either factor (the dual method's factor only
    # serves the rows whose answer was kept)
    redo = (~ok & (status == int(Status.SOLVED))) | (backward_set != active).any(-1)
    dual_factor = res.factor._replace(ok=ok & ~redo)
    rows = redo.nonzero().squeeze(-1)
    if len(rows) == 0:
        return Forward(x, z, y, status, iters, codes, dual_factor)
    # the other rows keep the dual method's factors: hard rows do not slow the whole batch
    sub = [t.index_select(0, rows) for t in (P, G, A, active, backward_set)]
    fac = MixedFactor(dual_factor, rows, _kkt.backward_factor(*sub))
    return Forward(x, z, y, status, iters, codes, fac)


def _certify_ill_conditioned(
    data: QPData,
    res: DualResult,
    ok: Tensor,
    cfg: SolverConfig,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """``(x, z, certified [B])`` for the rows the dual method left uncertified (not ``ok``:
    not converged, or ``P`` beyond :data:`MAX_DUAL_CONDITION`) and did not prove infeasible;
    ``certified`` is ``None`` where there are no such rows.

    A row is certified where a point is a KKT point to rounding
    (:func:`torchcbf.qp._kkt.kkt_point`) and no certificate of unboundedness
    (:func:`unbounded_solved`), whatever its conditioning: the method's own answer,
    or the solution on an active set (:func:`torchcbf.qp._kkt.solve_active`) guessed first by
    the method itself, then by up to :data:`PROX_STEPS` proximal steps (the dual method on
    ``P + rho I``, ``rho`` = :data:`PROX_WEIGHT` of ``P``'s largest diagonal entry, centred at
    the last step's point), whose conditioning the dual method handles and whose active set
    is, away from ties, the problem's own. The rows left go on to enumeration and the interior
    point method: a hard row costs a few small solves instead of their iterations. Testing
    whether any row needs this is one host synchronisation (none on a CPU)."""
    rows = ~ok & ~res.infeasible
    if not bool(rows.any()):
        return res.x, res.z, None
    x, z = res.x, res.z
    N, M, _ = data.sizes
    steps = dual_budget(cfg.max_iter, M, N)
    if isinstance(res.factor, NativeFactor) and _dual_native.can_certify():
        # the same steps in the C kernel, on the whole batch (no gathers); the rows it leaves
        # (a possible direction of unbounded descent, more active rows than variables) take
        # the steps below
        x, z, done = _dual_native.certify(
            *data[:4], rows, x, z, res.active, res.ok, eps=cfg.eps, max_iter=steps,
            prox_weight=PROX_WEIGHT, prox_steps=PROX_STEPS, rounding=cfg.rounding,
        )  # fmt: skip
        # a saddle, or a point far along a direction where P is singular to rounding, is no
        # answer; both need P singular to rounding, which one factorisation rules out
        odd = done & singular_to_rounding(data.P, data.P, cfg.rounding)
        if bool(odd.any()):
            bad = saddle_solved(data, x, odd, cfg.eps) | unbounded_solved(data, x, odd, cfg)
            done = done & ~bad
        left = rows & ~done
        if not bool(left.any()):
            return x, z, done
        res = res._replace(x=x, z=z)
        rows, certified = left, done
    else:
        certified = torch.zeros_like(rows)
    idx = rows.nonzero().squeeze(-1)
    sub = data.rows(idx)
    xs, zs, guess, conv = (t.index_select(0, idx) for t in (res.x, res.z, res.active, res.ok))
    ys = data.q.new_zeros(len(idx), 0)
    good = conv
    if bool(conv.any()):
        good = conv & _kkt.kkt_point(sub, xs, zs, ys)
        good = good & ~unbounded_solved(sub, xs, good, cfg) & ~saddle_solved(sub, xs, good, cfg.eps)
    rho = PROX_WEIGHT * sub.P.diagonal(dim1=-2, dim2=-1).amax(-1)
    Pr = sub.P + torch.diag_embed(rho.unsqueeze(-1).expand_as(sub.q))
    center = torch.zeros_like(xs)
    for step in range(PROX_STEPS + 1):
        if bool(good.all()):
            break
        if step == 0 and not bool((conv & ~good).any()):
            continue  # no converged row to polish: the method's active sets are no guess
        if step > 0:
            prox = solve_dual(Pr, sub.q - rho.unsqueeze(-1) * center, sub.G, sub.h,
                              eps=cfg.eps, max_iter=steps)  # fmt: skip
            guess = prox.active
            center = torch.where(prox.ok.unsqueeze(-1), prox.x, center)
        xp, zp, yp, solved = _kkt.solve_active(sub, guess, _kkt.POLISH_REFINE_STEPS)
        zp = zp.clamp_min(0.0)
        new = ~good & solved & _kkt.kkt_point(sub, xp, zp, yp)
        # a point far along a direction where P is singular to rounding is no answer (the
        # interior point method certifies such a row unbounded), nor a saddle
        new = new & ~unbounded_solved(sub, xp, new, cfg) & ~saddle_solved(sub, xp, new, cfg.eps)
        keep = new.unsqueeze(-1)
        xs, zs = torch.where(keep, xp, xs), torch.where(keep, zp, zs)
        good = good | new
    return x.index_copy(0, idx, xs), z.index_copy(0, idx, zs), certified.index_copy(0, idx, good)


def _ipm_fallback(
    data: QPData,
    cfg: SolverConfig,
    x0,
    x: Tensor,
    z: Tensor,
    y: Tensor,
    active: Tensor,
    ok: Tensor,
    iters: Tensor,
    codes: Tensor,
    infeasible: Tensor | None = None,
    none_fail: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Re-solve the rows with ``ok = False`` by the interior point method (with polish); rows
    marked ``infeasible`` (proved so by the first solver) are reported ``PRIMAL_INFEASIBLE``.

    Deciding whether any row needs it is the one host synchronisation of the exact paths
    (``bool(fail.any())``), spared where the caller found already that every row not
    ``infeasible`` is ``ok`` (``none_fail``). Returns ``(x, z, y, status, iterations,
    active, method)``, the method's codes (:data:`ANSWERED_BY`) updated from ``codes`` on
    the rows re-solved."""
    status = torch.where(ok, int(Status.SOLVED), int(Status.MAX_ITER))
    fail = ~ok
    if infeasible is not None:  # proved by the solver: PRIMAL_INFEASIBLE, x = 0, no re-solve
        status = torch.where(infeasible, int(Status.PRIMAL_INFEASIBLE), status)
        fail = fail & ~infeasible
    if none_fail or not bool(fail.any()):
        return x, z, y, status, iters, active, codes
    idx = fail.nonzero().squeeze(-1)
    N, M, E = data.sizes
    if (
        cfg.method != "enumerate"
        and num_candidates(M, E, N, cfg.pairs, cap=MAX_CANDIDATES_SMALL_BATCH)
        <= MAX_CANDIDATES_SMALL_BATCH
    ):
        # rows the exact method could not certify (degenerate vertices, ties): enumeration's
        # fixed cost is far below the interior point method's iterations; every such row
        # (not only a few: a row's answer must not depend on how many failed beside it)
        sub = data.rows(idx)
        en = _certified_enum(sub, cfg)
        if bool(en.ok.any()):
            keep = en.ok.unsqueeze(-1)
            x = x.index_copy(0, idx, torch.where(keep, en.x, x.index_select(0, idx)))
            z = z.index_copy(0, idx, torch.where(keep, en.z, z.index_select(0, idx)))
            y = y.index_copy(0, idx, torch.where(keep, en.y, y.index_select(0, idx)))
            active = active.index_copy(
                0, idx, torch.where(keep, en.active, active.index_select(0, idx))
            )
            status = status.index_copy(
                0, idx, torch.where(en.ok, int(Status.SOLVED), status.index_select(0, idx))
            )
            codes = codes.index_copy(0, idx[en.ok], _codes(int(en.ok.sum()), "enumerate", x.device))
            idx = idx[~en.ok]
            if len(idx) == 0:
                return x, z, y, status, iters, active, codes
    sub = data.rows(idx)
    x0s = None if x0 is None else x0.index_select(0, idx)
    # the batch's own fallback where it is proxsuite's dense solver first
    ipm = _ipm_routed if cfg.fallback == "auto_proxsuite" else _ipm
    xs, zs, ys, sts, its, acts, cs = ipm(sub, cfg, x0s)
    x, z, y = x.index_copy(0, idx, xs), z.index_copy(0, idx, zs), y.index_copy(0, idx, ys)
    status = status.index_copy(0, idx, sts)
    active = active.index_copy(0, idx, acts)
    iters = iters.index_copy(0, idx, its)
    return x, z, y, status, iters, active, codes.index_copy(0, idx, cs)


#: the methods, each ``(data, cfg, x0) -> Forward``; ``SolverConfig.method`` names the one
#: that solves a batch (``solve_qp`` picks it, :func:`torchcbf.qp.solve._config`)
SOLVERS: dict[str, Callable[[QPData, SolverConfig, Tensor | None], Forward]] = {
    "closed_form": _forward_closed_form,
    "active_set": _forward_dual,
    "eliminate": _forward_eliminated,
    "enumerate": _forward_enum,
    "ipm": _forward_ipm,
    "auto_proxsuite": _forward_routed,
    "outside": _forward_outside,
}


#: objectives whose largest entry lies within ``[1 / SCALE_BAND, SCALE_BAND]`` are solved
#: as given (:func:`data_scaling`)
SCALE_BAND = 16.0


class Scaling(NamedTuple):
    """The factor ``c [B]`` (a power of two) that scales a batch's objective."""

    c: Tensor

    def apply(self, P: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """The scaled objective ``(c P, c q)``; the minimiser is unchanged, the multipliers
        of the scaled problem are ``c`` times the original's."""
        return self.c.view(-1, 1, 1) * P, self.c.unsqueeze(-1) * q


def _inverse_power_of_two(v: Tensor) -> Tensor:
    """``1 / v`` rounded to a power of two (exact to scale by); 1 where ``v`` is 0."""
    pos = v > 0
    return torch.where(pos, torch.exp2(-torch.round(torch.log2(torch.where(pos, v, 1.0)))), 1.0)


def data_scaling(P: Tensor, q: Tensor) -> Scaling:
    """The :class:`Scaling` a batch is solved under (:class:`QPFunction`; for the outside
    backends only where it scales up): the objective's largest entry (of ``P`` and ``q``)
    brought near one, where it lies outside
    ``[1 / SCALE_BAND, SCALE_BAND]``. The interior point method's residual and gap tests
    and the polish's and the exact methods' multiplier tests carry absolute terms
    (``1 + scale``), which an objective of 1e-15 passes at a wrong point and one of 1e15
    fails at the right one; after the scaling they are relative. (Each row's own scale is
    already judged on its own, :func:`torchcbf.qp._kkt.row_scale`.)"""
    big = torch.maximum(P.abs().amax((-2, -1)), q.abs().amax(-1))
    band = (big >= 1.0 / SCALE_BAND) & (big <= SCALE_BAND)
    return Scaling(torch.where(band, 1.0, _inverse_power_of_two(big)))


def _cast(t: Tensor, dtype: torch.dtype) -> Tensor:
    """``t`` (float64) in ``dtype``, clamped to its finite range: a diverging last iterate
    (``MAX_ITER``) of 1e53 would become ``inf`` in float32."""
    if dtype == torch.float64:
        return t
    big = torch.finfo(dtype).max
    # cast, then clamp in place in the narrower dtype: the values of clamping first (an
    # overflow or an infinity becomes the largest finite value, NaN stays NaN), fewer bytes
    return t.to(dtype).clamp_(-big, big)


def _first_derivative_only(backward: Callable[..., Any]) -> Callable[..., Any]:
    """``backward`` run without a graph; under ``create_graph=True`` its gradients raise when
    differentiated again. ``torch.autograd.function.once_differentiable`` does that only
    where an incoming gradient carries a graph: a loss linear in ``x`` gives one that does
    not, and a second derivative then silently lacks the QP's own term."""

    @functools.wraps(backward)
    def wrapper(ctx: Any, *grads: Any) -> Any:
        # batched gradients (torch.autograd.grad(is_grads_batched=True), a vectorised
        # jacobian) run the backward under vmap
        refuse_transforms("solve_qp's backward", grads)
        with torch.no_grad():
            out = backward(ctx, *grads)
        if not torch.is_grad_enabled() or not ctx.graph_inputs:
            return out
        # an exact zero that reaches the inputs' graph (inf entries of h stay out of it), so
        # that differentiating a gradient towards anything before the QP meets the error
        link = sum(t.reshape(-1)[:0].sum() for t in ctx.graph_inputs)
        err = _functions.DelayedError(
            b"solve_qp gives first derivatives only: a second derivative through it (its "
            b"gradient computed with create_graph=True, then differentiated) is not available",
            len(out),
        )
        return err(*[None if g is None else g + link for g in out])

    return wrapper


class QPFunction(torch.autograd.Function):
    """``(P, q, G, h, A, b) -> (x, z, y, status, iterations, method)``, batched ``[B, ...]``
    (``method``: the :data:`ANSWERED_BY` code of each row).

    The torch backend solves the problem with its objective scaled (:func:`data_scaling`),
    the other backends with a small objective scaled up (their tolerances are absolute:
    proxsuite, OSQP, HiGHS and Clarabel reported an objective of 1e-10 solved at ``x = 0``)
    but a large one as given (scaled down, proxsuite called a feasible safety-filter QP of
    an arm, objective entries up to 1e3, primal infeasible); the multipliers (and the
    gradients) are scaled back."""

    @staticmethod
    def forward(ctx, P, q, G, h, A, b, cfg: SolverConfig, x0):  # noqa: D102
        dtype = q.dtype
        ctx.graph_inputs = tuple(t for t in (P, q, G, h, A, b) if t.requires_grad)
        data = QPData(P, q, G, h, A, b).to_float64()
        x0d = None if x0 is None else x0.detach().to(torch.float64)
        scaling = data_scaling(data.P, data.q)
        if cfg.backend != "torch":  # outside solvers: small objectives only (class docstring)
            scaling = Scaling(scaling.c.clamp_min(1.0))
        if q.device.type == "cpu" and bool((scaling.c == 1.0).all()):
            scaling = None  # nothing to scale (asking costs no device synchronisation here)
        if scaling is not None:
            Ps, qs = scaling.apply(data.P, data.q)
            data = data._replace(P=Ps, q=qs)
        x, z, y, status, iters, method, fac = _forward(data, cfg, x0d)
        ctx.fac = fac
        ctx.scaling = scaling
        ctx.save_for_backward(x, z, y, status)
        ctx.dtype = dtype
        ctx.dtypes = tuple(t.dtype for t in (P, q, G, h, A, b))
        ctx.mark_non_differentiable(status, iters, method)
        if scaling is not None:
            inv_c = (1.0 / scaling.c).unsqueeze(-1)
            z, y = z * inv_c, y * inv_c
        return _cast(x, dtype), _cast(z, dtype), _cast(y, dtype), status, iters, method

    @staticmethod
    @_first_derivative_only  # the factor is the forward's: a second derivative would be wrong
    def backward(ctx, gx, gz, gy, _gs, _gi, _gm):  # noqa: D102
        x, z, y, status = ctx.saved_tensors
        gx, gz, gy = (g.to(torch.float64) for g in (gx, gz, gy))
        scaling = ctx.scaling
        if scaling is not None:  # gradients of the scaled problem's outputs
            inv_c = (1.0 / scaling.c).unsqueeze(-1)
            gz, gy = gz * inv_c, gy * inv_c
        fac = ctx.fac
        if isinstance(fac, (DualFactor, NativeFactor, MixedFactor)):
            mixed = isinstance(fac, MixedFactor)
            wx, wz = dual_adjoints(fac.dual if mixed else fac, x, gx, gz)
            wy, lam = y, z  # y: [B, 0], no equality rows; z is zero off the active set
            if mixed:  # the rows of the KKT factor
                sub = [t.index_select(0, fac.rows) for t in (x, z, y, status, gx, gz, gy)]
                wx_r, wz_r, _, _ = _kkt.kkt_adjoints(fac.kkt, *sub)
                wx, wz = wx.index_copy(0, fac.rows, wx_r), wz.index_copy(0, fac.rows, wz_r)
        else:
            wx, wz, wy, lam = _kkt.kkt_adjoints(fac, x, z, y, status, gx, gz, gy)
        grads = _kkt.input_gradients(x, lam, y, wx, wz, wy, ctx.needs_input_grad[:6])
        if scaling is not None:  # the scaled P and q are c times the inputs
            dP, dq = grads[0], grads[1]
            dP = None if dP is None else dP * scaling.c.view(-1, 1, 1)
            dq = None if dq is None else dq * scaling.c.unsqueeze(-1)
            grads = (dP, dq, *grads[2:])
        grads = (None if g is None else g.to(d) for g, d in zip(grads, ctx.dtypes, strict=True))
        return (*grads, None, None)
