"""Dual active-set path of solve_qp (``method="active_set"``, the ``auto`` choice for large
batches): vs cvxpy, vs enumeration, gradients (gradcheck and vs the KKT-factor backward),
batch equals loop, degenerate rows, fallback of infeasible rows, float32. Every test runs
twice: on the torch implementation and on the C kernel (skipped where it was not built)."""

from __future__ import annotations

import pytest
import torch
from _problems import make_batch
from test_solve import check_against_cvxpy  # noqa: E402

from torchcbf.qp import Status, solve_qp
from torchcbf.qp._dual import _cho_solve, _cholesky, solve_dual

F64 = torch.float64
SHAPES = [  # n, m, box bounds (no equalities: the dual path does not take them)
    (2, 6, True),
    (3, 8, True),
    (4, 8, False),
    (6, 20, True),
    (8, 30, False),
]


@pytest.fixture(autouse=True)
def implementation(kernel):
    """Every test runs the torch implementation and the C kernel (where it is built)."""
    return kernel


def _args(batch):
    return (batch.Q, batch.p, batch.G, batch.h, None, None, batch.lb, batch.ub)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", SHAPES)
def test_active_set_matches_cvxpy(cvx, shape, dtype):
    n, m, bounds = shape
    batch = make_batch(40, n, m, 0, bounds, seed=300 + 11 * n + m, dtype=dtype)
    sol = solve_qp(*_args(batch), method="active_set")
    check_against_cvxpy(cvx, batch, sol, dtype, range(40))
    feas = torch.tensor([k != "infeasible" for k in batch.kind])
    assert (sol.status[feas] == Status.SOLVED).all()
    assert (sol.status[~feas] == Status.PRIMAL_INFEASIBLE).all()  # via the IPM fallback


@pytest.mark.parametrize("shape", SHAPES)
def test_auto_uses_active_set_for_large_batches_and_matches_enumeration(shape):
    n, m, bounds = shape
    batch = make_batch(300, n, m, 0, bounds, seed=400 + n, frac_infeasible=0.0)
    auto = solve_qp(*_args(batch))
    ipm = solve_qp(*_args(batch), method="ipm")
    assert (auto.status == Status.SOLVED).all()
    torch.testing.assert_close(auto.x, ipm.x, atol=1e-7, rtol=1e-7)
    torch.testing.assert_close(auto.lam, ipm.lam, atol=1e-6, rtol=1e-6)
    direct = solve_dual(
        0.5 * (batch.Q + batch.Q.mT),
        batch.p,
        batch.G if not bounds else _with_box(batch)[0],
        batch.h if not bounds else _with_box(batch)[1],
        eps=1e-7,
        max_iter=50,
    )
    assert direct.ok.all() and (direct.iterations > 0).any()
    torch.testing.assert_close(direct.x, auto.x, atol=1e-9, rtol=1e-9)


def _with_box(batch):
    n = batch.p.shape[-1]
    eye = torch.eye(n, dtype=batch.Q.dtype).expand(batch.Q.shape[0], n, n)
    G = torch.cat((batch.G, eye, -eye), -2)
    h = torch.cat((batch.h, batch.ub, -batch.lb), -1)
    return G, h


def test_batch_equals_loop():
    batch = make_batch(70, 4, 10, 0, True, seed=7, frac_infeasible=0.2)
    full = solve_qp(*_args(batch), method="active_set")
    for i in range(0, 70, 9):
        one = solve_qp(
            batch.Q[i], batch.p[i], batch.G[i], batch.h[i], lb=batch.lb[i], ub=batch.ub[i],
            method="active_set",
        )  # fmt: skip
        assert int(one.status) == int(full.status[i])
        torch.testing.assert_close(one.x, full.x[i], atol=1e-10, rtol=1e-10)


def test_gradcheck_through_active_set():
    batch = make_batch(6, 3, 5, 0, False, seed=11, frac_infeasible=0.0)
    Q = batch.Q.clone().requires_grad_(True)
    args = [t.clone().requires_grad_(True) for t in (batch.p, batch.G, batch.h)]

    def f(Q, p, G, h):
        sol = solve_qp(Q, p, G, h, method="active_set")
        return sol.x, sol.lam

    assert torch.autograd.gradcheck(f, (Q, *args), atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradients_match_kkt_factor_backward(dtype):
    batch = make_batch(50, 4, 8, 0, True, seed=13, frac_infeasible=0.0, dtype=dtype)
    w = torch.randn(50, 4, dtype=dtype, generator=torch.Generator().manual_seed(0))
    wl = torch.randn(50, 8, dtype=dtype, generator=torch.Generator().manual_seed(1))
    grads = {}
    for method in ("active_set", "enumerate"):
        leaves = [t.clone().requires_grad_(True) for t in _args(batch) if t is not None]
        sol = solve_qp(*leaves[:4], lb=leaves[4], ub=leaves[5], method=method)
        ((sol.x * w).sum() + (sol.lam * wl).sum()).backward()
        grads[method] = [t.grad for t in leaves]
    tol = 1e-8 if dtype == F64 else 2e-3
    for a, b in zip(grads["active_set"], grads["enumerate"], strict=True):
        torch.testing.assert_close(a, b, atol=tol, rtol=tol)


def test_degenerate_rows():
    """Duplicated and parallel constraints, a weakly active row, and an all-zero row."""
    Q = torch.eye(2, dtype=F64) * torch.tensor([[2.0], [1.0]], dtype=F64)
    p = torch.tensor([-4.0, -4.0], dtype=F64)
    G = torch.tensor(
        [
            [1.0, 0.0],
            [1.0, 0.0],  # duplicate of row 0
            [2.0, 0.0],  # parallel to row 0, same halfspace
            [0.0, 1.0],  # weakly active: unconstrained optimum in y is y = 4 = h
            [0.0, 0.0],  # 0 <= 1
        ],
        dtype=F64,
    )
    h = torch.tensor([1.0, 1.0, 2.0, 4.0, 1.0], dtype=F64)
    Qb, pb, Gb, hb = (t.expand(100, *t.shape) for t in (Q, p, G, h))
    sol = solve_qp(Qb, pb, Gb, hb, method="active_set")
    assert (sol.status == Status.SOLVED).all()
    torch.testing.assert_close(sol.x, torch.tensor([1.0, 4.0], dtype=F64).expand(100, 2))
    # stationarity with the returned multipliers: Qx + p + G'lam = 0, lam >= 0
    res = torch.einsum("bij,bj->bi", Qb, sol.x) + pb + torch.einsum("bmn,bm->bn", Gb, sol.lam)
    assert res.abs().max() < 1e-10 and (sol.lam >= 0).all()


def test_not_positive_definite_and_nonfinite_rows_fall_back():
    batch = make_batch(100, 3, 6, 0, False, seed=17, frac_infeasible=0.0)
    Q = batch.Q.clone()
    Q[3] = torch.diag(torch.tensor([1.0, 0.0, 1.0], dtype=F64))  # PSD, not PD
    p = batch.p.clone()
    p[5, 1] = float("nan")
    sol = solve_qp(Q, p, batch.G, batch.h, method="active_set")
    assert int(sol.status[5]) == Status.NON_FINITE
    assert int(sol.status[3]) in (Status.SOLVED, Status.DUAL_INFEASIBLE)
    others = torch.ones(100, dtype=torch.bool)
    others[[3, 5]] = False
    ref = solve_qp(batch.Q, batch.p, batch.G, batch.h, method="ipm")
    torch.testing.assert_close(sol.x[others], ref.x[others], atol=1e-7, rtol=1e-7)


def test_plane_cholesky_and_solve_against_torch():
    g = torch.Generator().manual_seed(3)
    A = torch.randn(50, 5, 5, generator=g, dtype=F64)
    P = A @ A.mT + 0.1 * torch.eye(5, dtype=F64)
    L, pd = _cholesky(P.permute(1, 2, 0).contiguous())
    assert pd.all()
    torch.testing.assert_close(L.permute(2, 0, 1), torch.linalg.cholesky(P))
    rhs = torch.randn(50, 5, 3, generator=g, dtype=F64)
    sol = _cho_solve(L, rhs.permute(1, 2, 0))
    torch.testing.assert_close(sol.permute(2, 0, 1), torch.linalg.solve(P, rhs))
    P[0, 2, 2] = -1.0
    assert not _cholesky(P.permute(1, 2, 0).contiguous())[1][0]


@pytest.mark.parametrize("method", ["auto", "active_set", "enumerate", "ipm"])
def test_empty_batch_gives_empty_answers(method):
    Q = torch.eye(3, dtype=F64).expand(0, 2, 3, 3)
    sol = solve_qp(Q, torch.zeros(0, 2, 3, dtype=F64), torch.zeros(4, 3, dtype=F64),
                   torch.ones(4, dtype=F64), method=method)  # fmt: skip
    assert sol.x.shape == (0, 2, 3) and sol.status.shape == (0, 2) and sol.lam.shape == (0, 2, 4)


def _row_and_grads(method, Q, p, G, h):
    leaves = [t.clone().requires_grad_(True) for t in (Q, p, G, h)]
    sol = solve_qp(*leaves, method=method)
    sol.x.sum().backward()
    return sol, [t.grad for t in leaves]


@pytest.mark.parametrize(
    "Q, p, G, h",
    [  # a large R P^-1 R' (no row may enter two slots) and a wide Q spectrum
        ([[1.0, 0.0], [0.0, 1.0]], [9.0, -7.0], [[-6000.0, 8000.0], [7000.0, 8000.0]], [1.0, 0]),
        ([[1e-8, 0.0], [0.0, 1e4]], [1.0, 1.0], [[-1.0, 0.0], [1.0, 1.0]], [1.0, 0.0]),
    ],
)
def test_badly_scaled_rows_match_enumeration_with_gradients(Q, p, G, h):
    data = [torch.tensor(t, dtype=F64) for t in (Q, p, G, h)]
    sol, grads = _row_and_grads("active_set", *data)
    ref, ref_grads = _row_and_grads("enumerate", *data)
    assert int(sol.status) == Status.SOLVED == int(ref.status)
    torch.testing.assert_close(sol.x, ref.x, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(sol.lam, ref.lam, atol=1e-9, rtol=1e-7)
    for a, b in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-7)


@pytest.mark.parametrize("method", ["active_set", "ipm", "enumerate"])
def test_tiny_row_is_judged_on_its_own_scale(method):
    """A row of norm 1e-6 next to one of norm 1e6: its violation of 1e-7 still counts."""
    Q = torch.eye(2, dtype=F64).expand(100, 2, 2)
    G = torch.tensor([[1e6, 0.0], [0.0, 1e-6]], dtype=F64)
    h = torch.tensor([1e6, -1e-7], dtype=F64)
    sol = solve_qp(Q, torch.zeros(100, 2, dtype=F64), G, h, method=method)
    assert (sol.status == Status.SOLVED).all()
    torch.testing.assert_close(sol.x, torch.tensor([0.0, -0.1], dtype=F64).expand(100, 2))


def test_rescaled_rows_give_the_same_solution():
    batch = make_batch(1000, 4, 8, 0, False, seed=12, frac_infeasible=0.0)
    sol = solve_qp(batch.Q, batch.p, 100.0 * batch.G, 100.0 * batch.h, method="active_set")
    assert (sol.status == Status.SOLVED).all()
    torch.testing.assert_close(sol.x, batch.x_star, atol=1e-9, rtol=1e-9)


def test_unfinished_rows_are_not_accepted():
    Q = torch.eye(2, dtype=F64).unsqueeze(0)
    G = torch.tensor([[[1.0, 0.0], [1.0, 1e-3]]], dtype=F64)
    h = torch.tensor([[-1.0, -1.0 - 5e-8]], dtype=F64)
    p = torch.zeros(1, 2, dtype=F64)
    assert not solve_dual(Q, p, G, h, eps=1e-7, max_iter=1).ok.any()
    full = solve_dual(Q, p, G, h, eps=1e-7, max_iter=50)
    assert full.ok.all()
    torch.testing.assert_close(full.z, torch.tensor([[0.95, 0.05]], dtype=F64))


def test_empty_batch_backward_and_equalities_rejected():
    p = torch.zeros(0, 3, dtype=F64, requires_grad=True)
    sol = solve_qp(torch.eye(3, dtype=F64).expand(0, 3, 3), p, torch.zeros(0, 2, 3, dtype=F64),
                   torch.zeros(0, 2, dtype=F64))  # fmt: skip
    sol.x.sum().backward()
    assert p.grad is not None and p.grad.shape == (0, 3)
    A, b = torch.ones(1, 2, dtype=F64), torch.ones(1, dtype=F64)
    with pytest.raises(ValueError, match="active_set"):
        solve_qp(torch.eye(2, dtype=F64), torch.zeros(2, dtype=F64), A=A, b=b, method="active_set")
