"""Unbounded problems are never SOLVED: ``Q`` positive semidefinite with a null direction
``d``, ``p'd < 0`` and ``G d < 0`` on every row (a recession direction; ``Q``'s zero
eigenvalue is only zero to rounding) are ``DUAL_INFEASIBLE`` on every method and dtype; and
no certificate is issued on problems with an optimum (singular ``Q`` bounded by the rows or a
box, and random strictly convex problems), which stay ``SOLVED`` and equal Clarabel's."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.qp import Status, solve_qp

METHODS = ("auto", "active_set", "enumerate", "ipm")
DTYPES = (torch.float64, torch.float32)


def _singular(B: int, n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``Q = L L'`` with ``L [n, n-1]`` (rank ``n - 1``, its zero eigenvalue rounded) and a
    unit null vector ``d`` of ``Q``."""
    f64 = torch.float64
    L = torch.randn(B, n, n - 1, generator=g, dtype=f64)
    d = torch.linalg.svd(L.mT).Vh[:, -1, :]
    return L @ L.mT, d


def recession(B: int, n: int = 4, m: int = 6, seed: int = 0):
    """Unbounded: ``Q d = 0`` (to rounding), ``p'd = -1``, ``G d`` in ``[-1.1, -0.1]``."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    Q, d = _singular(B, n, g)
    p = torch.randn(B, n, generator=g, dtype=f64)
    p = p - ((p * d).sum(-1, keepdim=True) + 1.0) * d
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    Gd = (G @ d.unsqueeze(-1)).squeeze(-1)
    target = -(torch.rand(B, m, generator=g, dtype=f64) + 0.1)
    G = G + (target - Gd).unsqueeze(-1) * d.unsqueeze(-2)
    h = torch.rand(B, m, generator=g, dtype=f64) + 0.1
    return Q, p, G, h


def bounded_singular(B: int, n: int = 4, m: int = 6, seed: int = 0, box: bool = False):
    """The same ``Q`` and ``p``, but the first row limits ``d`` (``G_0 d > 0``) or a box
    does: an optimum exists, far out along ``d`` when the limiting row is shallow."""
    Q, p, G, h = recession(B, n, m, seed)
    g = torch.Generator().manual_seed(seed + 1)
    d = torch.linalg.eigh(Q).eigenvectors[..., 0]
    d = d * torch.sign((p * d).sum(-1, keepdim=True)).neg()  # p'd < 0
    if not box:
        scale = torch.exp(torch.empty(B, 1, dtype=Q.dtype).uniform_(-4, 2, generator=g))
        G[:, 0] = G[:, 0] + (scale - (G[:, 0] * d).sum(-1, keepdim=True)) * d
    return Q, p, G, h


def _tol(dtype: torch.dtype) -> float:
    return 1e-6 if dtype == torch.float64 else 2e-3


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("seed", range(4))
def test_recession_direction_is_dual_infeasible(method, dtype, seed):
    Q, p, G, h = (t.to(dtype) for t in recession(40, seed=seed))
    sol = solve_qp(Q, p, G, h, method=method)
    counts = torch.bincount(sol.status, minlength=len(Status)).tolist()
    assert counts[Status.SOLVED] == 0, counts
    assert (sol.status == int(Status.DUAL_INFEASIBLE)).all(), counts
    assert (sol.x == 0).all()
    # one problem alone, and a few (the small-batch C path where it applies)
    assert int(solve_qp(Q[0], p[0], G[0], h[0], method=method).status) == Status.DUAL_INFEASIBLE
    few = solve_qp(Q[:3], p[:3], G[:3], h[:3], method=method)
    assert (few.status == int(Status.DUAL_INFEASIBLE)).all()


@pytest.mark.parametrize("method", METHODS)
def test_recession_direction_with_box_rows_infinite(method):
    Q, p, G, h = recession(10, seed=7)
    lb = torch.full_like(p, -torch.inf)
    ub = torch.full_like(p, torch.inf)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    assert (sol.status == int(Status.DUAL_INFEASIBLE)).all()


def _check_against_clarabel(cvx, sol, Q, p, G, h, lb=None, ub=None, tol=1e-6):
    for i in range(len(p)):
        args = [t[i].double().numpy() for t in (Q, p, G, h)]
        bounds = [None if t is None else t[i].double().numpy() for t in (lb, ub)]
        x_ref, _, status = cvx(*args, lb=bounds[0], ub=bounds[1])
        assert status == "optimal", (i, status)
        assert int(sol.status[i]) == int(Status.SOLVED), (i, int(sol.status[i]))
        x = sol.x[i].double()
        ref = torch.from_numpy(x_ref)
        assert float((x - ref).abs().max()) <= tol * (1 + float(ref.abs().max())), i


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
def test_bounded_singular_q_stays_solved(cvx, method, dtype):
    Q, p, G, h = (t.to(dtype) for t in bounded_singular(24, seed=3))
    sol = solve_qp(Q, p, G, h, method=method)
    # x can lie far along d (up to ~1e4): judge against Clarabel on the same (rounded) data
    _check_against_clarabel(cvx, sol, Q, p, G, h, tol=_tol(dtype) * 10)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
def test_singular_q_in_a_box_stays_solved(cvx, method, dtype):
    Q, p, G, h = (t.to(dtype) for t in bounded_singular(24, seed=4, box=True))
    lb, ub = -2 * torch.ones_like(p), 3 * torch.ones_like(p)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    _check_against_clarabel(cvx, sol, Q, p, G, h, lb, ub, tol=_tol(dtype))


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
def test_linear_program_in_a_box_stays_solved(cvx, method, dtype):
    """``Q = 0``: every direction is a null direction; the rows and the box bound it."""
    g = torch.Generator().manual_seed(5)
    B, n, m = 16, 3, 4
    Q = torch.zeros(B, n, n, dtype=torch.float64)
    p = torch.randn(B, n, generator=g, dtype=torch.float64)
    G = torch.randn(B, m, n, generator=g, dtype=torch.float64)
    h = torch.rand(B, m, generator=g, dtype=torch.float64) + 0.1
    Q, p, G, h = (t.to(dtype) for t in (Q, p, G, h))
    lb, ub = -torch.ones_like(p), torch.ones_like(p)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    _check_against_clarabel(cvx, sol, Q, p, G, h, lb, ub, tol=_tol(dtype))


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
def test_random_strictly_convex_problems_stay_solved(cvx, method, dtype):
    g = torch.Generator().manual_seed(6)
    B, n, m = 32, 4, 6
    R = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    Q = R @ R.mT / n + 1e-3 * torch.eye(n, dtype=torch.float64)
    p = 5 * torch.randn(B, n, generator=g, dtype=torch.float64)
    G = torch.randn(B, m, n, generator=g, dtype=torch.float64)
    h = torch.rand(B, m, generator=g, dtype=torch.float64) + 0.1
    Q, p, G, h = (t.to(dtype) for t in (Q, p, G, h))
    sol = solve_qp(Q, p, G, h, method=method)
    _check_against_clarabel(cvx, sol, Q, p, G, h, tol=_tol(dtype))


@pytest.mark.parametrize("n, m", [(4, 6), (100, 150)])
def test_unbounded_to_float32_rounding_one_problem_at_a_time(n, m):
    """The routes to proxsuite for one problem (its small-batch route, and the large
    problems' route beyond the C kernel) hand an unbounded problem on to the certificate."""
    for seed in range(2):
        Q, p, G, h = (t[0].float() for t in recession(1, n=n, m=m, seed=seed))
        sol = solve_qp(Q, p, G, h)
        assert int(sol.status) == Status.DUAL_INFEASIBLE, sol.path
        assert (sol.x == 0).all()


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", ("auto", "enumerate", "ipm"))
@pytest.mark.parametrize("B", [1, 5, 64])
def test_recession_direction_inside_the_equalities_is_dual_infeasible(B, method, dtype):
    """``Q = vv'``, ``v'x = 0.5`` and a loose row ``v'x <= 100``: the null direction ``d`` of
    ``Q`` keeps every row, and ``p'd < 0``. Eliminating the equality leaves a reduced Hessian
    that is rounding alone, which the dual method must not take for curvature. In float32
    the rounding makes ``Q`` indefinite on about half the rows and the far stationary point
    a saddle (``p'x > 0``: the objective falls along ``-x``), which no method may take for a
    minimiser either."""
    g = torch.Generator().manual_seed(B)
    v = torch.randn(B, 2, generator=g, dtype=torch.float64) * 0.2
    d = torch.stack([-v[:, 1], v[:, 0]], -1)
    Q = v.unsqueeze(-1) * v.unsqueeze(-2)
    p = -d + 0.1 * v
    A = G = v.unsqueeze(-2)
    b, h = (
        torch.full((B, 1), 0.5, dtype=torch.float64),
        torch.full((B, 1), 100.0, dtype=torch.float64),
    )
    args = [t.to(dtype) for t in (Q, p, G, h, A, b)]
    for grad in (False, True):
        p_in = args[1].clone().requires_grad_(grad)
        sol = solve_qp(args[0], p_in, *args[2:], method=method)
        assert (sol.status == int(Status.DUAL_INFEASIBLE)).all(), (sol.path, sol.status)
        assert (sol.x == 0).all()


def saddle_family(B: int, n: int, m: int, seed: int):
    """``Q`` of rank ``n - 1`` rounded to float32 (its zero eigenvalue lands a little either
    side of zero), ``p`` rising along the null direction ``d``, and rows that leave the ray
    along ``d`` open and close the one against it: bounded, with the minimiser on a row, and
    where the eigenvalue went negative a stationary point far along ``d`` (a saddle)."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    L = torch.randn(B, n, n - 1, generator=g, dtype=f64)
    Q = (L @ L.mT).float().double()
    d = torch.linalg.eigh(Q).eigenvectors[..., 0]
    p = torch.randn(B, n, generator=g, dtype=f64)
    d = d * torch.sign((p * d).sum(-1, keepdim=True))
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    target = -(torch.rand(B, m, generator=g, dtype=f64) + 0.2)
    G = G + (target - (G @ d.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1) * d.unsqueeze(-2)
    h = torch.rand(B, m, generator=g, dtype=f64) + 0.5
    return tuple(t.float().double() for t in (Q, p, G, h))


def least_stationary_objective(Q, p, G, h) -> float:
    """The least objective over the feasible stationary points of every face of ``G x <=
    h`` (numpy, float64): the minimum of a bounded QP, convex or not."""
    import itertools

    import numpy as np

    Q, p, G, h = (t.numpy() for t in (Q, p, G, h))
    n, best = len(p), math.inf
    for k in range(n + 1):
        for face in map(list, itertools.combinations(range(len(h)), k)):
            K = np.block([[Q, G[face].T], [G[face], np.zeros((k, k))]])
            rhs = np.concatenate([-p, h[face]])
            sol = np.linalg.lstsq(K, rhs, rcond=1e-12)[0]
            x = sol[:n]
            stationary = np.abs(K @ sol - rhs).max() <= 1e-8 * (1 + np.abs(rhs).max())
            if stationary and (G @ x - h).max() <= 1e-9 * (1 + np.abs(h).max()):
                best = min(best, 0.5 * x @ Q @ x + p @ x)
    return best


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", ("auto", "active_set", "ipm"))
def test_a_saddle_of_a_rounded_singular_q_is_never_solved(kernel, method, dtype, seed):
    """Where rounding leaves ``Q`` a little indefinite, every row is SOLVED at the minimiser
    (the least objective of the brute-force reference), never at the far saddle that a
    proximal step or the polish can converge to."""
    n = 2 + seed % 3
    Q, p, G, h = saddle_family(5, n, 6, seed)
    sol = solve_qp(*(t.to(dtype) for t in (Q, p, G, h)), method=method)
    assert (sol.status == Status.SOLVED).all(), sol.status
    x = sol.x.double()
    got = 0.5 * torch.einsum("bi,bij,bj->b", x, Q, x) + (p * x).sum(-1)
    for i in range(5):
        ref = least_stationary_objective(Q[i], p[i], G[i], h[i])
        assert abs(float(got[i]) - ref) <= 1e-4 * (1 + abs(ref)), (i, float(got[i]), ref)


@pytest.mark.parametrize("B", [1, 8, 64])
@pytest.mark.parametrize("grad", [False, True])
def test_an_indefinite_box_problem_is_solved_at_its_minimiser_not_a_degenerate_corner(B, grad):
    """A separable problem with some curvatures negative on the box [-1, 1]^n: a corner
    where every bound is tight with a zero multiplier (the gradient zero there) is a KKT
    point but no minimiser; every batch size and path answers the global minimiser, which
    the separable problem gives coordinate by coordinate."""
    gen = torch.Generator().manual_seed(B)
    n = 4
    curv = torch.randn(B, n, generator=gen, dtype=torch.float64)
    curv[:, 0] = -1.0  # one negative curvature in each row
    # p so that the point x* = -sign pattern is a corner with zero gradient: q_i x_i + p_i = 0
    corner = torch.where(torch.rand(B, n, generator=gen) < 0.5, -1.0, 1.0).double()
    p = -curv * corner
    Q = torch.diag_embed(curv)
    candidates = torch.stack([-torch.ones_like(p), torch.ones_like(p),
                              (-p / curv).clamp(-1.0, 1.0)], -1)  # fmt: skip
    values = 0.5 * curv.unsqueeze(-1) * candidates**2 + p.unsqueeze(-1) * candidates
    best = values.amin(-1).sum(-1)
    pq = p.clone().requires_grad_(grad)
    sol = solve_qp(Q, pq, lb=-1.0, ub=1.0)
    assert bool((sol.status == 0).all())
    x = sol.x.detach()
    f = (0.5 * curv * x**2 + p * x).sum(-1)
    torch.testing.assert_close(f, best, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_problems_without_rows_on_every_method(method):
    """No rows at all: a singular convex problem with an optimum is SOLVED at it, and one
    with negative curvature (unbounded below) is never SOLVED."""
    f64 = torch.float64
    for Q, p, x in (
        (torch.zeros(2, 2, dtype=f64), torch.zeros(2, dtype=f64), None),
        (torch.diag(torch.tensor([1.0, 0.0], dtype=f64)), torch.tensor([1.0, 0.0], dtype=f64),
         -1.0),
    ):  # fmt: skip
        for batch in ((), (3,)):
            sol = solve_qp(Q.expand(*batch, 2, 2), p.expand(*batch, 2), method=method)
            assert bool((sol.status == Status.SOLVED).all())
            if x is not None:
                torch.testing.assert_close(sol.x[..., 0], torch.full(batch, x, dtype=f64))
    sol = solve_qp(-torch.eye(2, dtype=f64), torch.zeros(2, dtype=f64), method=method)
    assert int(sol.status) != Status.SOLVED


@pytest.mark.parametrize("method", ["auto", "active_set", "enumerate", "ipm"])
def test_negative_curvature_along_an_open_ray_is_unbounded(method):
    """``Q`` with a negative eigenvalue whose eigenvector ``v`` no row blocks (``G v = 0``):
    the objective falls without bound along ``v`` from any feasible point, and every row is
    ``DUAL_INFEASIBLE`` with ``x = 0``, not a stationary point reported ``SOLVED``; the
    same rows in a box are solved at their minimiser."""
    gen = torch.Generator().manual_seed(11)
    f64 = torch.float64
    B = 6
    U = torch.linalg.qr(torch.randn(B, 3, 3, generator=gen, dtype=f64)).Q
    Q = U @ torch.diag_embed(torch.tensor([1.0, 0.5, -0.3], dtype=f64).expand(B, 3)) @ U.mT
    v = U[..., 2]
    G = torch.randn(B, 2, 3, generator=gen, dtype=f64)
    G = G - (G @ v.unsqueeze(-1)) * v.unsqueeze(-2)
    h = torch.rand(B, 2, generator=gen, dtype=f64) + 0.5
    p = torch.randn(B, 3, generator=gen, dtype=f64)
    sol = solve_qp(Q, p, G, h, method=method)
    assert (sol.status == int(Status.DUAL_INFEASIBLE)).all(), sol.status
    assert (sol.x == 0).all()
    one = torch.ones(B, 3, dtype=f64)
    boxed = solve_qp(Q, p, G, h, lb=-one, ub=one, method=method)
    assert (boxed.status == int(Status.SOLVED)).all(), boxed.status
    x = boxed.x
    got = 0.5 * torch.einsum("bi,bij,bj->b", x, Q, x) + (p * x).sum(-1)
    eye = torch.eye(3, dtype=f64).expand(B, 3, 3)
    for i in range(B):
        Gb = torch.cat([G[i], eye[i], -eye[i]]).numpy()
        hb = torch.cat([h[i], one[i], one[i]]).numpy()
        ref = least_stationary_objective(Q[i], p[i], torch.tensor(Gb), torch.tensor(hb))
        assert abs(float(got[i]) - ref) <= 1e-6 * (1 + abs(ref)), (i, float(got[i]), ref)
