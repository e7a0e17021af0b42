"""proxsuite and qpsolvers backends, elastic (soft) rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, solve_qp

F64 = torch.float64


@pytest.mark.parametrize("backend", ["proxsuite", "qpsolvers:clarabel", "qpsolvers:osqp"])
def test_backend_statuses_and_solutions_match_torch(backend):
    if backend == "proxsuite":
        pytest.importorskip("proxsuite")
    else:
        qpsolvers = pytest.importorskip("qpsolvers")
        if backend.split(":")[1] not in qpsolvers.available_solvers:
            pytest.skip(f"{backend} not installed")
    batch = make_batch(24, 4, 6, 1, True, seed=21)
    args = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    ref = solve_qp(*args)
    eps = 1e-9 if backend != "qpsolvers:osqp" else 1e-5
    with torch.no_grad():
        sol = solve_qp(*args, backend=backend, eps=eps)
    infeasible = torch.tensor([k == "infeasible" for k in batch.kind])
    assert (sol.status[infeasible] != Status.SOLVED).all()
    if backend != "qpsolvers:osqp":  # OSQP may stop at max-iter instead of certifying
        assert (sol.status[infeasible] == Status.PRIMAL_INFEASIBLE).all()
    solved = sol.status == Status.SOLVED
    assert solved[~infeasible].float().mean() >= (0.9 if backend != "qpsolvers:osqp" else 0.5)
    tol = 1e-6 if backend != "qpsolvers:osqp" else 1e-2
    torch.testing.assert_close(sol.x[solved], ref.x[solved], atol=tol, rtol=0)
    assert (sol.x[infeasible] == 0).all()


def test_qpsolvers_backend_refuses_gradients():
    Q = torch.eye(2, dtype=F64)
    p = torch.ones(2, dtype=F64, requires_grad=True)
    with pytest.raises(ValueError, match="forward-only"):
        solve_qp(Q, p, backend="qpsolvers:clarabel")
    with pytest.raises(ValueError, match="not installed"), torch.no_grad():
        solve_qp(Q, p, backend="qpsolvers:nonexistent")


def test_proxsuite_backend_gradients_match_torch():
    batch = make_batch(6, 3, 4, 0, True, seed=10, frac_infeasible=0.0)
    grads = []
    for backend in ("torch", "proxsuite"):
        p = batch.p.clone().requires_grad_(True)
        G = batch.G.clone().requires_grad_(True)
        sol = solve_qp(batch.Q, p, G, batch.h, lb=batch.lb, ub=batch.ub, backend=backend)
        assert (sol.status == Status.SOLVED).all()
        grads.append(torch.autograd.grad((sol.x**2).sum(), (p, G)))
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)


def test_soft_rows_make_infeasible_problems_feasible(cvx):
    # hard box |u| <= 1 and a CBF-like row u1 + u2 >= 3 that cannot hold in the box
    B = 5
    Q = torch.eye(2, dtype=F64).expand(B, 2, 2)
    u_nom = torch.linspace(-1, 1, B, dtype=F64).unsqueeze(-1).expand(B, 2)
    p = -u_nom
    G = torch.tensor([[-1.0, -1.0], [1.0, -1.0]], dtype=F64).expand(B, 2, 2)
    h = torch.tensor([-3.0, 5.0], dtype=F64).expand(B, 2)
    hard = solve_qp(Q, p, G, h, lb=-1.0, ub=1.0)
    assert (hard.status == Status.PRIMAL_INFEASIBLE).all()
    w = torch.tensor([10.0, 0.0], dtype=F64)  # row 0 soft, row 1 hard
    sol = solve_qp(Q, p, G, h, lb=-1.0, ub=1.0, soft=w)
    assert (sol.status == Status.SOLVED).all()
    torch.testing.assert_close(sol.x, torch.ones(B, 2, dtype=F64), atol=1e-8, rtol=0)
    torch.testing.assert_close(sol.slack[:, 0], torch.ones(B, dtype=F64), atol=1e-8, rtol=0)
    assert (sol.slack[:, 1] == 0).all()
    # reference: the elastic problem written out explicitly for cvxpy
    import numpy as np

    Qa = np.diag([1.0, 1.0, 10.0])
    for i in range(B):
        pa = np.concatenate([p[i].numpy(), [10.0]])
        Ga = np.array([[-1.0, -1.0, -1.0], [1.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        ha = np.array([-3.0, 5.0, 0.0])
        lb = np.array([-1.0, -1.0, -np.inf])
        ub = np.array([1.0, 1.0, np.inf])
        xr, _, st = cvx(Qa, pa, Ga, ha, None, None, lb, ub)
        assert st == "optimal"
        np.testing.assert_allclose(sol.x[i].numpy(), xr[:2], atol=1e-6)
        np.testing.assert_allclose(float(sol.slack[i, 0]), xr[2], atol=1e-6)


def test_soft_exact_penalty_when_feasible():
    batch = make_batch(16, 3, 4, 0, False, seed=30, frac_infeasible=0.0)
    hard = solve_qp(batch.Q, batch.p, batch.G, batch.h)
    soft = torch.full((4,), 100.0, dtype=F64)  # above every multiplier: penalty is exact
    sol = solve_qp(batch.Q, batch.p, batch.G, batch.h, soft=soft)
    torch.testing.assert_close(sol.x, hard.x, atol=1e-7, rtol=0)
    assert sol.slack.abs().max() < 1e-7
    torch.testing.assert_close(sol.lam, hard.lam, atol=1e-6, rtol=0)
    inf_w = solve_qp(
        batch.Q, batch.p, batch.G, batch.h, soft=torch.full((4,), float("inf"), dtype=F64)
    )
    torch.testing.assert_close(inf_w.x, hard.x, atol=1e-7, rtol=0)


@pytest.mark.parametrize("method", ["ipm", "auto", "enumerate"])
def test_a_soft_rows_slack_is_the_least_its_x_needs(method):
    """The slack reported is ``max(0, G x - h)`` of the answer: the interior point method
    left a weightless slack (weight 1e-6 beside an objective of order one) at 0.10 on a row
    satisfied by 0.52."""
    Q = torch.tensor([[0.806, -0.504, 0.229], [-0.504, 3.444, 0.123], [0.229, 0.123, 1.275]])
    p = torch.tensor([-3.128, 3.956, 2.243])
    G = torch.tensor([[-1.326, -1.241, -0.103], [-0.950, 0.618, -0.238],
                      [0.0245, -0.491, -0.0591], [-1.565, 0.426, -1.482]])  # fmt: skip
    h = torch.tensor([0.4236, 0.1344, 0.8726, 0.0248])
    A, b = torch.tensor([[0.417, 1.000, 0.601]]), torch.tensor([0.011])
    lb, ub = torch.tensor([-0.166, -0.0981, -0.217]), torch.tensor([0.107, 0.111, 0.255])
    soft = torch.tensor([1e-6, 2.0, 0.0, 5.0])
    data = [t.double() for t in (Q, p, G, h, A, b, lb, ub)]
    sol = solve_qp(*data, soft=soft.double(), method=method)
    violation = data[2] @ sol.x - data[3]
    assert float(violation[0]) < -0.5 and float(sol.slack[0]) == 0.0
    torch.testing.assert_close(sol.slack, violation.clamp_min(0.0) * (soft > 0), atol=0, rtol=0)


def _watched_problem(eps_abs: float, P, q, G, h):
    """proxsuite's dense problem ``min x'Px/2 + q'x`` s.t. ``Gx <= h`` to ``eps_abs``."""
    proxqp = pytest.importorskip("proxsuite").proxqp
    n, m = q.shape[-1], h.shape[-1]
    qp = proxqp.dense.QP(n, 0, m, False)
    qp.settings.eps_abs = eps_abs
    qp.settings.eps_rel = 0.0
    qp.settings.verbose = False
    qp.init(P, q, None, None, G, np.full(m, -1e20), h)
    return qp


def test_a_watched_solve_stops_where_the_iterates_run_along_a_direction_of_descent():
    """Unbounded to float32's rounding (``Q``'s zero eigenvalue rounded): proxsuite runs its
    whole budget on it; the watched solve stops after its two short runs."""
    from test_unbounded import recession

    from torchcbf.qp._backends import WATCH_ITER, descends, solve_watched

    Q, p, G, h = (t[0].float().double().numpy() for t in recession(1, seed=0))
    qp = _watched_problem(1e-9, Q, p, G, h)
    inf = np.full((1, 4), np.inf)

    def descending(d):
        return descends(Q[None], p[None], G[None], np.zeros((1, 0, 4)), -inf, inf,
                        np.zeros((1, 6), bool), d[None], 1e-5)  # fmt: skip

    assert solve_watched(qp, 10_000, descending) is None
    assert qp.results.info.iter_ext <= WATCH_ITER  # outer iterations of the second run


def test_a_watched_solve_goes_on_to_the_answer_of_one_solve():
    """A problem that needs more iterations than the watch (a tolerance near rounding): the
    watched solve ends where one plain solve does, and counts the iterations of all its runs."""
    from torchcbf.qp._backends import WATCH_ITER, solve_watched

    rng = np.random.default_rng(0)
    n, m = 30, 60
    U = np.linalg.qr(rng.standard_normal((n, n)))[0]
    P = U @ np.diag(np.logspace(-7, 0, n)) @ U.T
    q, G, h = 10 * rng.standard_normal(n), rng.standard_normal((m, n)), rng.random(m)
    plain = _watched_problem(1e-14, P, q, G, h)
    plain.settings.max_iter = 10_000
    plain.solve()
    watched = _watched_problem(1e-14, P, q, G, h)
    seen = []
    taken = solve_watched(watched, 10_000, lambda d: seen.append(d) or False)
    assert len(seen) == 1  # both short runs ended unsolved, and it went on
    assert taken is not None and taken >= 2 * WATCH_ITER
    np.testing.assert_allclose(watched.results.x, plain.results.x, atol=1e-9, rtol=0)


def test_proxsuite_backend_solved_rows_are_minimisers():
    """proxsuite stops on feasibility and stationarity unless asked to close the duality
    gap: on problems with rows near their bounds it called points 1% above the minimum
    solved. Every row it calls solved is the torch method's minimiser to eps."""
    pytest.importorskip("proxsuite")
    g = torch.Generator().manual_seed(3)
    B, n, m = 40, 3, 4
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT + 0.5 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    slack = torch.rand(B, m, generator=g, dtype=F64)
    slack[:, : m // 2] = 0.0
    h = (G @ x0.unsqueeze(-1)).squeeze(-1) + slack + 0.05
    ref = solve_qp(Q, p, G, h)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h, backend="proxsuite")
    solved = sol.status == Status.SOLVED
    assert solved.float().mean() >= 0.9 and bool((ref.status == Status.SOLVED).all())
    err = (sol.x - ref.x).abs().amax(-1) / (1.0 + ref.x.abs().amax(-1))
    assert float(err[solved].max()) <= 1e-6, err


def test_proxsuites_claims_of_infeasibility_are_checked():
    """proxsuite calls a few strictly feasible problems (the origin inside every row by 0.2
    or more) primal infeasible; those rows are solved again and take a certified answer,
    while a truly infeasible row keeps its status."""
    pytest.importorskip("proxsuite")
    g = torch.Generator().manual_seed(0)
    B, n, m = 1024, 2, 5
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = 0.2 + torch.rand(B, m, generator=g, dtype=F64)
    # row 0 infeasible: x_0 <= -1 and -x_0 <= -1
    G[0, :2] = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=F64)
    h[0, :2] = -1.0
    ref = solve_qp(Q, p, G, h)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h, backend="proxsuite")
    assert int(ref.status[0]) == int(sol.status[0]) == Status.PRIMAL_INFEASIBLE
    assert bool((ref.status[1:] == Status.SOLVED).all())
    assert bool((sol.status[1:] == Status.SOLVED).all())
    err = (sol.x - ref.x)[1:].abs().amax(-1) / (1.0 + ref.x[1:].abs().amax(-1))
    assert float(err.max()) <= 1e-6


@pytest.mark.parametrize("backend", ["torch", "proxsuite", "qpsolvers:clarabel"])
def test_multipliers_of_infinite_bounds_are_zero(backend):
    """``lam_lb`` and ``lam_ub`` are exactly zero where the bound is infinite, whatever an
    outside solver leaves there (1e-12), and the finite bounds keep theirs."""
    if backend == "proxsuite":
        pytest.importorskip("proxsuite")
    elif backend != "torch":
        qpsolvers = pytest.importorskip("qpsolvers")
        if "clarabel" not in qpsolvers.available_solvers:
            pytest.skip("clarabel not installed")
    Q = torch.eye(2, dtype=F64).expand(3, 2, 2)
    p = torch.tensor([[-3.0, 3.0], [1.0, -1.0], [0.5, 0.5]], dtype=F64)
    lb = torch.tensor([-math.inf, -1.0], dtype=F64)
    ub = torch.tensor([1.0, math.inf], dtype=F64)
    with torch.no_grad():
        sol = solve_qp(Q, p, lb=lb, ub=ub, backend=backend)
    assert (sol.status == Status.SOLVED).all()
    assert (sol.lam_lb[:, 0] == 0).all() and (sol.lam_ub[:, 1] == 0).all()
    torch.testing.assert_close(sol.lam_ub[:, 0], torch.tensor([2.0, 0.0, 0.0], dtype=F64),
                               atol=1e-6, rtol=0)  # fmt: skip
    torch.testing.assert_close(sol.lam_lb[:, 1], torch.tensor([2.0, 0.0, 0.0], dtype=F64),
                               atol=1e-6, rtol=0)  # fmt: skip


def test_an_outside_answer_is_solved_only_where_it_is_a_kkt_point():
    """qpsolvers' proxqp at its own tolerances stops far from some minimisers: every row
    reported SOLVED is the torch answer."""
    qpsolvers = pytest.importorskip("qpsolvers")
    if "proxqp" not in qpsolvers.available_solvers:
        pytest.skip("proxqp is not installed")
    batch = make_batch(48, 3, 5, 0, False, seed=3)
    args = (batch.Q, batch.p, batch.G, batch.h)
    ref = solve_qp(*args)
    with torch.no_grad():
        sol = solve_qp(*args, backend="qpsolvers:proxqp", eps=1e-7)
    solved = (sol.status == Status.SOLVED) & (ref.status == Status.SOLVED)
    assert bool(solved.any())
    assert not bool(((sol.status == Status.SOLVED) & (ref.status != Status.SOLVED)).any())
    torch.testing.assert_close(sol.x[solved], ref.x[solved], atol=1e-5, rtol=0)
