"""Badly scaled QPs: objectives scaled by 1e-15..1e15 and rows by 1e-6..1e6, per row of a
batch, both dtypes, every method. A SOLVED answer is right, and every problem Clarabel solves
(after scaling the objective by ``1 / max|Q, p|`` and each row by ``1 / max|G_i|``, which it
needs) is SOLVED."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import cvxpy_solve

from torchcbf.qp import Status, solve_qp

F64 = torch.float64
OBJECTIVE_SCALES = (1e-15, 1e-10, 1e-5, 1.0, 1e5, 1e10, 1e15)
METHODS = ("auto", "active_set", "enumerate", "ipm")


def _problems(kind: str, seed: int, copies: int = 2):
    """One batch ``(Q, p, G, h, A, b, lb, ub)`` in float64: ``copies`` rows per objective scale
    of :data:`OBJECTIVE_SCALES`, every row of ``G`` (and ``A``) scaled by its own 10^U(-6, 6);
    feasible at ``x = 0``. ``kind``: ``"box"`` (rows and box bounds) or ``"eq"`` (rows and
    one equality)."""
    g = torch.Generator().manual_seed(seed)
    B, n, m = copies * len(OBJECTIVE_SCALES), 3, 5
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.2 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    obj = torch.tensor(OBJECTIVE_SCALES, dtype=F64).repeat_interleave(copies)
    Q, p = Q * obj.view(-1, 1, 1), p * obj.unsqueeze(-1)
    rows = 10.0 ** (12 * torch.rand(B, m, generator=g, dtype=F64) - 6)
    G = torch.randn(B, m, n, generator=g, dtype=F64) * rows.unsqueeze(-1)
    h = (torch.rand(B, m, generator=g, dtype=F64) + 0.1) * rows
    A = b = lb = ub = None
    if kind == "box":
        lb = -torch.rand(B, n, generator=g, dtype=F64) - 0.2
        ub = torch.rand(B, n, generator=g, dtype=F64) + 0.2
    else:
        erow = 10.0 ** (12 * torch.rand(B, 1, generator=g, dtype=F64) - 6)
        A = torch.randn(B, 1, n, generator=g, dtype=F64) * erow.unsqueeze(-1)
        b = torch.zeros(B, 1, dtype=F64)
    return Q, p, G, h, A, b, lb, ub


def _reference(Q, p, G, h, A, b, lb, ub):
    """Clarabel on the scaled float64 copy of each row: ``(x [B, n], solved [B])``."""
    xs, ok = [], []
    for i in range(Q.shape[0]):
        Qi, pi, Gi, hi = (t[i].double().numpy() for t in (Q, p, G, h))
        c = 1.0 / max(np.abs(Qi).max(), np.abs(pi).max())
        r = 1.0 / np.abs(Gi).max(-1)
        Ai = bi = None
        if A is not None:
            e = 1.0 / np.abs(A[i].double().numpy()).max(-1)
            Ai, bi = A[i].double().numpy() * e[:, None], b[i].double().numpy() * e
        lbi = None if lb is None else lb[i].double().numpy()
        ubi = None if ub is None else ub[i].double().numpy()
        x, _, status = cvxpy_solve(c * Qi, c * pi, Gi * r[:, None], hi * r, Ai, bi, lbi, ubi)
        ok.append(status == "optimal")
        xs.append(x if x is not None else np.zeros(Qi.shape[0]))
    return np.stack(xs), np.array(ok)


def _check(sol, ref_x, ref_ok, dtype, where):
    status = sol.status.numpy()
    x = sol.x.detach().double().numpy()
    err = np.abs(x - ref_x).max(-1) / (1.0 + np.abs(ref_x).max(-1))
    tol = 1e-6 if dtype == F64 else 2e-3
    solved = status == int(Status.SOLVED)
    wrong = np.flatnonzero(solved & ((err > tol) | ~ref_ok))
    assert len(wrong) == 0, f"{where}: wrong SOLVED rows {wrong.tolist()}: {err[wrong]}"
    failed = np.flatnonzero(ref_ok & ~solved)
    assert len(failed) == 0, f"{where}: false failures {failed.tolist()}: {status[failed]}"


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("kind", ["box", "eq"])
def test_badly_scaled_rows_solved_right_on_every_method(dtype, kind):
    data = [None if t is None else t.to(dtype) for t in _problems(kind, seed=7)]
    ref_x, ref_ok = _reference(*data)
    assert ref_ok.mean() > 0.9  # the family is meant to be solvable
    Q, p, G, h, A, b, lb, ub = data
    for method in METHODS:
        if kind == "eq" and method == "active_set":
            continue
        for grad in (False, True):  # the real-time C path (few rows) and the general path
            Qg = Q.clone().requires_grad_(grad)
            sol = solve_qp(Qg, p, G, h, A, b, lb, ub, method=method)
            _check(sol, ref_x, ref_ok, dtype, f"{method} grad={grad} ({sol.path})")


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["float64", "float32"])
def test_tiny_objective_interior_point(dtype):
    """Q and p of 1e-15: the interior point method's tests are relative to the data's scale
    (it reported SOLVED at a point 9 away from the minimiser)."""
    g = torch.Generator().manual_seed(2074117147)
    B, n, m = 16, 2, 2
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = (L @ L.mT / n + 0.5 * torch.eye(n, dtype=F64)) * 1e-15
    p = torch.randn(B, n, generator=g, dtype=F64) * 1e-15
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = torch.rand(B, m, generator=g, dtype=F64) + 0.1
    data = [t.to(dtype) for t in (Q, p, G, h)]
    ref_x, ref_ok = _reference(*data, None, None, None, None)
    assert ref_ok.all()
    for method in METHODS:
        _check(solve_qp(*data, method=method), ref_x, ref_ok, dtype, method)


def _tight_problems(seed: int, B: int = 16, n: int = 4, m: int = 6):
    """``(Q, p, G, h)`` float64, row ``i`` drawn from seed ``seed + i``, half of its rows
    tight at a random point (active sets of several rows)."""
    rows = []
    for i in range(B):
        g = torch.Generator().manual_seed(seed + i)
        L = torch.randn(n, n, generator=g, dtype=F64)
        Q = L @ L.T + 0.5 * torch.eye(n, dtype=F64)
        p = 3.0 * torch.randn(n, generator=g, dtype=F64)
        G = torch.randn(m, n, generator=g, dtype=F64)
        x0 = torch.randn(n, generator=g, dtype=F64)
        slack = torch.rand(m, generator=g, dtype=F64)
        slack[: m // 2] = 0.0
        rows.append((Q, p, G, G @ x0 + slack + 0.05))
    return tuple(torch.stack(t) for t in zip(*rows, strict=True))


@pytest.mark.parametrize("rows", [1e16, 1e14, 1e10, 1e-10, 1e-14])
def test_rows_of_any_magnitude_every_method(rows):
    """Every row of ``G, h`` scaled by one factor far from 1 (multipliers of 1e-16 at 1e16):
    the feasible set and the minimiser do not change. Enumeration's sign test on the
    multipliers was absolute and took a wrong active set SOLVED (0.73 off)."""
    Q, p, G, h = _tight_problems(200)
    ref_x, ref_ok = _reference(Q, p, G, h, None, None, None, None)
    assert ref_ok.all()
    for method in METHODS:
        _check(solve_qp(Q, p, G * rows, h * rows, method=method), ref_x, ref_ok, F64, method)


@pytest.mark.parametrize("seed", [200, 31])
def test_a_problem_in_other_units_every_method(seed):
    """Objective x 1e4, variables in micro-units (x 1e6), rows x 1e8: ``Q`` of 1e16, ``G``
    of 1e14, multipliers of 1e-21 after the solver's own scaling. Every method gives the
    minimiser in the new units."""
    Q, p, G, h = _tight_problems(seed)
    ref_x, ref_ok = _reference(Q, p, G, h, None, None, None, None)
    assert ref_ok.all()
    obj, dx, con = 1e4, 1e6, 1e8
    for method in METHODS:
        sol = solve_qp(Q * obj * dx * dx, p * obj * dx, G * con * dx, h * con, method=method)
        _check(sol._replace(x=sol.x * dx), ref_x, ref_ok, F64, method)


def test_ill_conditioned_problems_with_huge_rows_are_certified():
    """``P`` of condition up to 1e10 (random eigenvectors), rows scaled by 1e12: the
    stationarity of the right answer misses by 1e4 epsilons of its terms (multipliers of
    1e-15 on rows of 1e12 cancel against an objective gradient of 1e-6), which left rows
    NUMERICAL_ERROR; no wrong answer is certified either."""
    g = torch.Generator().manual_seed(17)
    B, n, m = 64, 4, 6
    U, _ = torch.linalg.qr(torch.randn(B, n, n, generator=g, dtype=F64))
    power = 10 * torch.rand(B, 1, generator=g, dtype=F64)
    Q = U @ torch.diag_embed(torch.logspace(0, 1, n, dtype=F64).expand(B, n) ** power) @ U.mT
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    x0 = torch.randn(B, n, 1, generator=g, dtype=F64)
    slack = torch.rand(B, m, generator=g, dtype=F64)
    slack[:, : m // 2] = 0.0
    h = (G @ x0).squeeze(-1) + slack + 0.05
    ref = solve_qp(Q, p, G, h, method="ipm")
    assert (ref.status == Status.SOLVED).all()
    for method in METHODS:
        sol = solve_qp(Q, p, G * 1e12, h * 1e12, method=method)
        solved = sol.status == Status.SOLVED
        err = (sol.x - ref.x).abs().amax(-1) / (1.0 + ref.x.abs().amax(-1))
        assert (err[solved] <= 1e-6).all(), (method, err[solved].max())
        assert int(solved.sum()) >= B - 1, (method, sol.status)


def test_multipliers_and_gradients_of_a_scaled_problem():
    """The multipliers come back in the problem's own units (stationarity holds), and the
    gradients match finite differences where the scaling is far from one."""
    Q, p, G, h, A, b, lb, ub = _problems("eq", seed=3, copies=1)
    k = OBJECTIVE_SCALES.index(1e5)
    Q, p, G, h, A, b = (t[k : k + 1] for t in (Q, p, G, h, A, b))
    sol = solve_qp(Q, p, G, h, A, b, method="ipm")
    assert int(sol.status) == Status.SOLVED
    grad = Q @ sol.x.unsqueeze(-1) + p.unsqueeze(-1)
    grad = grad + G.mT @ sol.lam.unsqueeze(-1) + A.mT @ sol.nu.unsqueeze(-1)
    assert grad.abs().max() <= 1e-8 * p.abs().max()
    # gradients: moderate scales, so that finite differences resolve them
    Qm, pm = Q / 1e5 * 1e3, p / 1e5 * 1e3
    Gm, hm = G / G.abs().amax(-1, keepdim=True) * 1e-2, h / G.abs().amax(-1) * 1e-2
    w = torch.randn(1, 3, generator=torch.Generator().manual_seed(0), dtype=F64)

    def loss(Q_, p_, G_, h_, A_, b_):
        s = solve_qp(Q_, p_, G_, h_, A_, b_, method="ipm")
        return (s.x * w).sum() + s.lam.sum() * 1e-3

    args = [t.clone().requires_grad_(True) for t in (Qm, pm, Gm, hm, A, b)]
    assert torch.autograd.gradcheck(loss, args, eps=1e-7, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("scale", [1e-150, 1e-10, 1e10])
@pytest.mark.parametrize(
    "route",
    ["auto", "proxsuite", "qpsolvers:clarabel", "qpsolvers:proxqp", "qpsolvers:highs"],
)
def test_outside_solvers_see_an_objective_of_any_magnitude(route, scale):
    """Q and p of 1e-150 .. 1e10 on the routes to outside solvers (``"auto"`` with 65
    variables goes to proxsuite straight from the inputs): every SOLVED row is the
    minimiser of the unscaled problem, multipliers in the problem's own units (these
    solvers' tolerances are absolute: they "solved" ``1e-10 (Q, p)`` at ``x = 0``)."""
    pytest.importorskip("proxsuite")
    if route.startswith("qpsolvers:"):
        qpsolvers = pytest.importorskip("qpsolvers")
        if route.split(":")[1] not in qpsolvers.available_solvers:
            pytest.skip(f"{route} is not installed")
    g = torch.Generator().manual_seed(5)
    B, n, m = 2, 65, 2
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.2 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = torch.rand(B, m, generator=g, dtype=F64) + 0.1
    lb, ub = -torch.ones(B, n, dtype=F64), torch.ones(B, n, dtype=F64)
    ref_x, ref_ok = _reference(Q, p, G, h, None, None, lb, ub)
    assert ref_ok.all()
    kw = {"backend": route} if route != "auto" else {}
    with torch.no_grad():
        sol = solve_qp(Q * scale, p * scale, G, h, lb=lb, ub=ub, **kw)
    if route == "auto":
        assert sol.path == "small_proxsuite"
    solved = (sol.status == int(Status.SOLVED)).numpy()
    # a large objective goes to an outside solver as given (it may stop at its iteration
    # limit: a status), and qpsolvers' proxqp stops there on one row of the small ones
    if route == "auto" or (scale < 1 and route != "qpsolvers:proxqp"):
        assert solved.all(), sol.status
    err = np.abs(sol.x.numpy() - ref_x).max(-1)
    assert (err[solved] <= 1e-5).all(), err
    # stationarity of (Q, p) with the multipliers as returned
    grad = scale * (Q @ sol.x.unsqueeze(-1) + p.unsqueeze(-1)).squeeze(-1)
    grad = grad + (G.mT @ sol.lam.unsqueeze(-1)).squeeze(-1) + sol.lam_ub - sol.lam_lb
    assert (grad.abs().amax(-1)[solved] <= 1e-5 * scale * p.abs().max()).all()
