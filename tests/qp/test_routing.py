"""``method="auto"`` on a few CPU QPs beyond the C kernel's reach: proxsuite's dense solver
straight from the inputs (``small_proxsuite``, no gradients) or inside the differentiable
map (``auto_proxsuite``), each answer verified by torchcbf, polished, and otherwise handed
to torchcbf's own methods."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, solve_qp
from torchcbf.qp import _function as qp_function

pytest.importorskip("proxsuite")
F64 = torch.float64


def _mid_size(seed: int, n: int = 80, m: int = 60, k: int = 10):
    """A feasible QP with ``n > 64`` variables, rows tight at a known point, equalities and
    a box: ``P`` positive semidefinite of rank ``n / 2`` (linear-program-like directions)."""
    g = torch.Generator().manual_seed(seed)
    L = torch.randn(n, n // 2, generator=g, dtype=F64)
    P = L @ L.mT / n
    x0 = torch.rand(n, generator=g, dtype=F64) - 0.5
    G = torch.randn(m, n, generator=g, dtype=F64)
    h = G @ x0 + torch.rand(m, generator=g, dtype=F64) * (torch.rand(m, generator=g) < 0.5)
    A = torch.randn(k, n, generator=g, dtype=F64)
    b = A @ x0
    p = torch.randn(n, generator=g, dtype=F64)
    return P, p, G, h, A, b, -torch.ones(n, dtype=F64), torch.ones(n, dtype=F64)


@pytest.mark.parametrize("seed", [0, 1])
def test_mid_size_problem_matches_clarabel_and_the_interior_point_path(cvx, seed):
    data = _mid_size(seed)
    with torch.no_grad():
        direct = solve_qp(*data)
    assert direct.path == "small_proxsuite"
    ref, obj, st = cvx(*(t.numpy() for t in data))
    assert st == "optimal" and int(direct.status) == Status.SOLVED
    x = direct.x.numpy()
    P, p = data[0].numpy(), data[1].numpy()
    assert abs(0.5 * x @ P @ x + p @ x - obj) <= 1e-8 * (1.0 + abs(obj))
    ipm = solve_qp(*data, method="ipm")
    assert int(ipm.status) == Status.SOLVED
    assert abs(float(0.5 * ipm.x @ data[0] @ ipm.x + data[1] @ ipm.x) - obj) <= 1e-7 * (
        1 + abs(obj)
    )
    # stationarity with the returned multipliers (bounds included)
    P, p, G, h, A, b = data[:6]
    r = P @ direct.x + p + G.T @ direct.lam + A.T @ direct.nu + direct.lam_ub - direct.lam_lb
    assert float(r.abs().max()) < 1e-9


def test_gradients_through_a_routed_answer_match_the_interior_point_path():
    data = _mid_size(3)
    grads = {}
    for method in ("auto", "ipm"):
        p = data[1].clone().requires_grad_()
        h = data[3].clone().requires_grad_()
        sol = solve_qp(data[0], p, data[2], h, *data[4:], method=method)
        assert int(sol.status) == Status.SOLVED
        if method == "auto":
            assert sol.path == "auto_proxsuite"
        grads[method] = torch.autograd.grad((sol.x * torch.linspace(-1, 1, 80, dtype=F64)).sum(),
                                            (p, h))  # fmt: skip
    for a, b in zip(grads["auto"], grads["ipm"], strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)


def test_equality_problems_one_at_a_time_equal_the_batch():
    batch = make_batch(20, 4, 6, 2, True, seed=4, frac_infeasible=0.0)
    args = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    full = solve_qp(*args)
    assert full.path == "active_set_native"
    for i in range(6):
        one = solve_qp(*(t[i] for t in args))
        assert one.path == "small_native" and int(one.status) == int(full.status[i])
        for name in ("x", "lam", "nu", "lam_lb", "lam_ub"):
            torch.testing.assert_close(getattr(one, name), getattr(full, name)[i], atol=1e-8,
                                       rtol=0)  # fmt: skip


def test_infinite_rows_are_ignored_on_the_direct_path():
    # Q singular (which the dual method never takes), so proxsuite takes the problem:
    # x1 = x2, x3 <= 1 - 2 x1 leaves x1^2 - 1, least at x = (0, 0, 1)
    Q = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    p = -torch.ones(3, dtype=F64)
    G = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0]], dtype=F64)
    h = torch.tensor([1.0, torch.inf], dtype=F64)
    A = torch.tensor([[1.0, -1.0, 0.0]], dtype=F64)
    b = torch.zeros(1, dtype=F64)
    sol = solve_qp(Q, p, G, h, A, b)
    assert sol.path == "small_proxsuite" and int(sol.status) == Status.SOLVED
    torch.testing.assert_close(sol.x, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    assert float(sol.lam[1]) == 0.0


@pytest.mark.parametrize("case", ["infeasible", "unbounded", "nan"])
def test_unsolved_problems_take_the_general_path(case):
    Q = torch.eye(3, dtype=F64)
    p = torch.zeros(3, dtype=F64)
    A = torch.tensor([[1.0, 1.0, 0.0]], dtype=F64)
    b = torch.ones(1, dtype=F64)
    G = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    h = torch.zeros(2, dtype=F64)
    expect = Status.SOLVED
    if case == "infeasible":  # x1 + x2 = 1 with x1, x2 <= 0
        expect = Status.PRIMAL_INFEASIBLE
    elif case == "unbounded":  # no curvature along x3, which the objective rewards
        Q = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
        p = torch.tensor([0.0, 0.0, -1.0], dtype=F64)
        h = torch.ones(2, dtype=F64)
        expect = Status.DUAL_INFEASIBLE
    else:
        p = torch.tensor([0.0, float("nan"), 0.0], dtype=F64)
        expect = Status.NON_FINITE
    sol = solve_qp(Q, p, G, h, A, b)
    assert sol.path != "small_proxsuite"
    assert int(sol.status) == expect


def test_a_row_proxsuite_leaves_is_solved_by_the_interior_point_method(monkeypatch):
    """Where proxsuite fails (simulated), the routed rows are solved by torchcbf itself."""
    from torchcbf.qp import _backends

    real = _backends.solve_proxsuite

    def failing(*args, **kwargs):
        x, s, z, y, st, it = real(*args, **kwargs)
        return x, s, z, y, torch.full_like(st, int(Status.MAX_ITER)), it

    monkeypatch.setattr(_backends, "solve_proxsuite", failing)
    data = _mid_size(5)
    p = data[1].clone().requires_grad_()
    sol = solve_qp(data[0], p, *data[2:])
    assert sol.path == "auto_proxsuite" and int(sol.status) == Status.SOLVED
    ref = solve_qp(data[0], p.detach(), *data[2:], method="ipm")
    torch.testing.assert_close(sol.x.detach(), ref.x, atol=1e-6, rtol=0)
    sol.x.sum().backward()
    assert torch.isfinite(p.grad).all()


def _badly_scaled(seed: int, n: int = 70, m: int = 90, k: int = 4):
    """A feasible QP whose rows are scaled by factors from 1e-6 to 1e6 (their slacks at a
    known point likewise): more than 64 variables and equality rows, so that a small batch
    is routed to proxsuite; ``P`` of rank ``n / 3`` plus 1e-9 I."""
    g = torch.Generator().manual_seed(seed)
    L = torch.randn(n, n // 3, generator=g, dtype=F64)
    P = L @ L.mT + 1e-9 * torch.eye(n, dtype=F64)
    p = torch.randn(n, generator=g, dtype=F64)
    G = torch.randn(m, n, generator=g, dtype=F64)
    G = G * torch.exp(torch.empty(m, 1, dtype=F64).uniform_(-6, 6, generator=g))
    x0 = torch.randn(n, generator=g, dtype=F64)
    slack = torch.rand(m, generator=g, dtype=F64)
    h = G @ x0 + slack * torch.exp(torch.empty(m, dtype=F64).uniform_(-6, 6, generator=g))
    A = torch.randn(k, n, generator=g, dtype=F64)
    return P, p, G, h, A, A @ x0


@pytest.mark.filterwarnings("ignore:Solution may be inaccurate")  # Clarabel on the scaling
def test_a_row_the_tighter_run_leaves_is_solved_to_the_callers_tolerance(monkeypatch, cvx):
    """Where proxsuite fails (simulated) the interior point method runs to a tolerance tighter
    than the caller's; on a problem it cannot reach that on (rows scaled over twelve decades)
    the row is solved again to the caller's, as ``method="ipm"`` solves it."""
    from torchcbf.qp import _backends

    real = _backends.solve_proxsuite

    def failing(*args, **kwargs):
        x, s, z, y, st, it = real(*args, **kwargs)
        return x, s, z, y, torch.full_like(st, int(Status.MAX_ITER)), it

    monkeypatch.setattr(_backends, "solve_proxsuite", failing)
    P, p, G, h, A, b = _badly_scaled(22)
    tight = solve_qp(P, p, G, h, A, b, method="ipm", eps=qp_function.ROUTE_FALLBACK_EPS)
    assert int(tight.status) != Status.SOLVED  # the case this test is about
    sol = solve_qp(P, p.clone().requires_grad_(), G, h, A, b)
    assert sol.path == "auto_proxsuite" and int(sol.status) == Status.SOLVED
    own = solve_qp(P, p, G, h, A, b, method="ipm")
    _, ref, _ = cvx(*(t.numpy() for t in (P, p, G, h, A, b)))
    for x in (sol.x.detach(), own.x):
        objective = float(0.5 * x @ P @ x + p @ x)
        assert abs(objective - ref) <= 1e-6 * max(1.0, abs(ref))


def test_routing_applies_to_small_batches_only():
    data = _mid_size(6)
    big = [t.expand(5, *t.shape) for t in data]
    sol = solve_qp(*big)
    assert sol.path == "ipm"
    assert (sol.status == Status.SOLVED).all()
    assert qp_function.ROUTE_EPS <= 1e-9
    one = solve_qp(*data)
    np.testing.assert_allclose(sol.x[0].numpy(), one.x.numpy(), atol=1e-6)


def test_problems_the_kernel_fits_are_not_routed():
    """A problem of the C kernel's shape (no equalities, at most 64 variables) with a
    positive definite Q is served by torchcbf's own methods at every batch size, also where
    the kernel declines it (condition 1e8): routing cannot make its status depend on the
    batch size. A singular Q, which the dual method never takes, may go to proxsuite."""
    c, s_ = 0.6, 0.8
    rot = torch.tensor([[c, -s_], [s_, c]], dtype=F64)
    Q = rot @ torch.diag(torch.tensor([1.0, 1e-8], dtype=F64)) @ rot.T
    p = torch.tensor([-1.0, -1.0], dtype=F64)
    G = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    h = torch.tensor([2.0, 1.0], dtype=F64)
    one = solve_qp(Q, p, G, h)
    many = solve_qp(Q.expand(9, 2, 2), p.expand(9, 2), G.expand(9, 2, 2), h.expand(9, 2))
    assert "proxsuite" not in one.path and "proxsuite" not in many.path
    assert int(one.status) == Status.SOLVED and (many.status == Status.SOLVED).all()
    torch.testing.assert_close(one.x, many.x[0])
    singular = torch.diag(torch.tensor([1.0, 0.0], dtype=F64))
    sol = solve_qp(singular, p, G, h)
    assert sol.path == "small_proxsuite" and int(sol.status) == Status.SOLVED
    torch.testing.assert_close(sol.x, torch.tensor([1.0, 1.0], dtype=F64))
    # an indefinite Q is not routed: proxsuite, made for convex problems, ran its whole
    # budget (about 50 s) on one unbounded along its negative curvature
    indefinite = torch.diag(torch.tensor([1.0, -1.0], dtype=F64))
    sol = solve_qp(indefinite, p, G[:1] * torch.tensor([1.0, 0.0], dtype=F64), h[:1])
    assert "proxsuite" not in sol.path and int(sol.status) == Status.DUAL_INFEASIBLE


def test_dependent_equality_rows_are_never_solved_wrong(cvx):
    """Seven equality rows of rank six (one row a combination of two others), a ``Q`` of rank
    ``n - 1``: the multipliers are free along the dependence, and proxsuite's answer with
    multipliers of 1e18 passed a stationarity test scaled by them. Every SOLVED answer has
    Clarabel's objective."""
    n, k = 8, 7
    for seed in range(40):
        g = torch.Generator().manual_seed(seed)
        L = torch.randn(n, n - 1, generator=g, dtype=F64)
        p = 10 * torch.randn(n, generator=g, dtype=F64)
        A = torch.randn(k, n, generator=g, dtype=F64)
        A[-1] = A[0] + 2 * A[1]
        x0 = torch.randn(n, generator=g, dtype=F64)
        G = torch.randn(1, n, generator=g, dtype=F64)
        G = torch.cat([G, G + 1e-9 * torch.randn(1, n, generator=g, dtype=F64)])
        Q, b, h = L @ L.mT, A @ x0, G @ x0 + 0.1
        sol = solve_qp(Q, p, G, h, A, b)
        assert int(sol.status) == Status.SOLVED, (seed, sol.path)
        _, ref, _ = cvx(*(t.numpy() for t in (Q, p, G, h, A, b)))
        objective = float(0.5 * sol.x @ Q @ sol.x + p @ sol.x)
        assert abs(objective - ref) <= 1e-6 * max(1.0, abs(ref)), (seed, sol.path)


@pytest.mark.parametrize("k", [7, 8, 10])
def test_dependent_equality_rows_in_a_batch_are_solved_on_an_independent_set(cvx, k):
    """A batch of twelve with ``k`` equality rows in 8 variables: for ``k = 7`` rows 0-5 of
    rank six (b in their range, row 3 excepted) and rows 6-11 of full rank; for ``k >= 8``
    every row of rank six; two nearly equal inequality rows. Every consistent row is SOLVED
    with Clarabel's objective (dependent rows left the KKT systems of enumeration and the
    interior point method singular: NUMERICAL_ERROR), the inconsistent one is
    PRIMAL_INFEASIBLE, a row solved alone equals its answer in the batch, and the gradients
    equal central differences."""
    g = torch.Generator().manual_seed(3)
    B, n = 12, 8
    L = torch.randn(B, n, n - 1, generator=g, dtype=F64)
    p = 10 * torch.randn(B, n, generator=g, dtype=F64)
    A = torch.randn(B, k, n, generator=g, dtype=F64)
    if k < n:
        A[:6, -1] = A[:6, 0] + 2 * A[:6, 1]
    else:
        A = A[..., :6] @ torch.randn(B, 6, n, generator=g, dtype=F64)
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, 1, n, generator=g, dtype=F64)
    G = torch.cat([G, G + 1e-9 * torch.randn(B, 1, n, generator=g, dtype=F64)], dim=1)
    Q = L @ L.mT
    shift = torch.zeros(B, k, dtype=F64)
    shift[3, -1] = 1.0

    def solve(p, x0, rows=slice(None)):
        b = (A[rows] @ x0.unsqueeze(-1)).squeeze(-1) + shift[rows]
        h = (G[rows] @ x0.unsqueeze(-1)).squeeze(-1) + 0.1
        return solve_qp(Q[rows], p, G[rows], h, A[rows], b), b, h

    pr, x0r = p.clone().requires_grad_(True), x0.clone().requires_grad_(True)
    sol, b, h = solve(pr, x0r)
    consistent = torch.arange(B) != 3
    assert (sol.status[consistent] == Status.SOLVED).all(), sol.status
    assert int(sol.status[3]) == Status.PRIMAL_INFEASIBLE
    for i in consistent.nonzero().flatten().tolist():
        data = (t[i].detach().numpy() for t in (Q, p, G, h, A, b))
        _, ref, _ = cvx(*data)
        x = sol.x[i].detach()
        objective = float(0.5 * x @ Q[i] @ x + p[i] @ x)
        assert abs(objective - ref) <= 1e-6 * max(1.0, abs(ref)), (i, objective, ref)
    alone, _, _ = solve(p[1:2], x0[1:2], slice(1, 2))
    torch.testing.assert_close(alone.x[0], sol.x[1].detach(), rtol=1e-8, atol=1e-8)
    weights = torch.randn(B, n, generator=g, dtype=F64) * consistent.unsqueeze(-1)
    (sol.x * weights).sum().backward()
    for value, grad, which in ((p, pr.grad, 0), (x0, x0r.grad, 1)):
        d = torch.randn(B, n, generator=g, dtype=F64) * consistent.unsqueeze(-1)
        e = 1e-6
        args = [p, x0]
        args[which] = value + e * d
        up = (solve(*args)[0].x * weights).sum()
        args[which] = value - e * d
        down = (solve(*args)[0].x * weights).sum()
        assert abs(float((up - down) / (2 * e)) - float((grad * d).sum())) <= 1e-5 * (
            1.0 + abs(float((grad * d).sum()))
        )


def test_a_nan_row_of_a_small_batch_is_non_finite_and_the_others_solved():
    """The check of whether some Q is singular reads the finite rows alone (LAPACK refuses
    a NaN matrix, for the whole batch)."""
    n = 4
    Q = (torch.eye(n, dtype=torch.float64) + 0.1).repeat(2, 1, 1)
    Q[1, 0, 1] = float("nan")
    p, G, h = torch.ones(2, n).double(), torch.ones(2, 1, n).double(), torch.ones(2, 1).double()
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
        want = solve_qp(Q[:1], p[:1], G[:1], h[:1])
    assert sol.status.tolist() == [int(Status.SOLVED), int(Status.NON_FINITE)]
    torch.testing.assert_close(sol.x[:1], want.x)


def test_rows_of_any_magnitude_on_the_direct_route():
    """A singular Q and rows scaled by 1e16 (the feasible set unchanged): proxsuite's
    tolerances are absolute, so it sees the rows at unit length."""
    g = torch.Generator().manual_seed(0)
    v = torch.randn(4, 1, generator=g, dtype=torch.float64)
    Q, p = v @ v.T, torch.randn(4, generator=g, dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    G = torch.cat([torch.randn(8, 4, generator=g, dtype=torch.float64), eye, -eye])
    h = torch.cat([torch.rand(8, generator=g, dtype=torch.float64) + 0.5,
                   torch.full((8,), 3.0, dtype=torch.float64)])  # fmt: skip
    with torch.no_grad():
        base = solve_qp(Q, p, G, h)
        for scale in (1e8, 1e16):
            sol = solve_qp(Q, p, scale * G, scale * h)
            assert sol.path == "small_proxsuite" and int(sol.status) == int(Status.SOLVED)
            torch.testing.assert_close(sol.x, base.x, atol=1e-8, rtol=0)
