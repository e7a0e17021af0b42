"""solve_qp (torch backend): accuracy vs cvxpy, statuses, batching, shapes and errors."""

from __future__ import annotations

import math
import shutil
import sysconfig

import numpy as np
import pytest
import torch
from _problems import TEN_THOUSAND_SHAPES, make_batch

from torchcbf.qp import QPSolution, Status, _dual_native, solve_qp

F64 = torch.float64
TOL = {torch.float64: 1e-6, torch.float32: 1e-3}
SHAPES = [  # n, m, equalities, box bounds
    (2, 1, 0, False),
    (2, 6, 0, True),
    (4, 8, 1, False),
    (5, 16, 0, True),
    (8, 5, 2, True),
    (12, 64, 3, True),
]


def _np(t):
    return None if t is None else t.detach().double().cpu().numpy()


def _objective(Q, p, x):
    return 0.5 * float(x @ Q @ x) + float(p @ x)


def check_against_cvxpy(cvx, batch, sol, dtype, rows):
    """Every feasible row solved to tolerance, every infeasible row flagged (none solved)."""
    tol = TOL[dtype]
    for i in rows:
        data = [
            _np(t[i]) if t is not None else None
            for t in (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
        ]
        x_ref, obj_ref, status = cvx(*data)
        st = int(sol.status[i])
        if batch.kind[i] == "infeasible":
            assert status == "infeasible"
            assert st == Status.PRIMAL_INFEASIBLE, (i, st)
            continue
        assert status == "optimal"
        assert st == Status.SOLVED, (i, st, batch.kind[i])
        x = _np(sol.x[i])
        scale = 1.0 + np.abs(x_ref).max()
        assert np.abs(x - x_ref).max() <= tol * scale, (i, np.abs(x - x_ref).max())
        obj = _objective(data[0], data[1], x)
        assert abs(obj - obj_ref) <= tol * (1.0 + abs(obj_ref)), (i, obj, obj_ref)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", SHAPES)
def test_matches_cvxpy(cvx, shape, dtype):
    n, m, me, bounds = shape
    batch = make_batch(40, n, m, me, bounds, seed=7 * n + m, dtype=dtype)
    sol = solve_qp(batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    assert sol.x.dtype == dtype and sol.x.shape == (40, n)
    check_against_cvxpy(cvx, batch, sol, dtype, range(40))
    # the constructed optimum is an independent second reference
    feas = torch.tensor([k != "infeasible" for k in batch.kind])
    err = (sol.x[feas] - batch.x_star[feas]).abs().max()
    assert err <= TOL[dtype] * (1 + batch.x_star.abs().max())


def test_multipliers_satisfy_kkt():
    batch = make_batch(64, 4, 6, 1, True, seed=3)
    sol = solve_qp(batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    ok = sol.status == Status.SOLVED
    grad = (
        torch.einsum("bij,bj->bi", batch.Q, sol.x)
        + batch.p
        + torch.einsum("bmn,bm->bn", batch.G, sol.lam)
        + torch.einsum("bmn,bm->bn", batch.A, sol.nu)
        - sol.lam_lb
        + sol.lam_ub
    )
    assert grad[ok].abs().max() < 1e-8
    assert (sol.lam[ok] >= 0).all() and (sol.lam_lb[ok] >= 0).all()
    slack = batch.h - torch.einsum("bmn,bn->bm", batch.G, sol.x)
    assert (sol.lam * slack)[ok].abs().max() < 1e-8


def test_dual_infeasible_detected():
    # LP direction of unbounded descent: min -x1 s.t. x2 <= 1 (x1 free), Q = 0
    Q = torch.zeros(3, 2, 2, dtype=F64)
    Q[1, 0, 0] = 1.0  # row 1 is bounded (x1 quadratic), row 2 bounded by a constraint
    p = torch.tensor([[-1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]], dtype=F64)
    G = torch.tensor([[[0.0, 1.0]], [[0.0, 1.0]], [[1.0, 0.0]]], dtype=F64)
    h = torch.ones(3, 1, dtype=F64)
    G = torch.cat((G, torch.tensor([0.0, -1.0], dtype=F64).expand(3, 1, 2)), 1)
    h = torch.cat((h, torch.ones(3, 1, dtype=F64)), 1)
    sol = solve_qp(Q, p, G, h)
    assert sol.status.tolist() == [Status.DUAL_INFEASIBLE, Status.SOLVED, Status.SOLVED]
    torch.testing.assert_close(sol.x[1], torch.tensor([1.0, sol.x[1, 1]], dtype=F64))
    assert float(sol.x[2, 0]) == pytest.approx(1.0, abs=1e-8)
    assert (sol.x[0] == 0).all()


@pytest.mark.parametrize("method", ["ipm", "auto"])
def test_strictly_convex_problem_with_a_large_q_is_not_called_unbounded(method):
    """A bounded problem (P = 1, -10 <= x <= 1, q = -1e8) is not certified dual infeasible:
    that certificate is only for rows whose P is not positive definite."""
    G = torch.tensor([[1.0], [-1.0]], dtype=F64)
    h = torch.tensor([1.0, 10.0], dtype=F64)
    sol = solve_qp(torch.eye(1, dtype=F64), torch.tensor([-1e8], dtype=F64), G, h, method=method)
    assert int(sol.status) == Status.SOLVED
    assert float(sol.x[0]) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("method", ["ipm", "auto"])
@pytest.mark.parametrize("curvature", [1e-8, 1e-6, 1e-4])
def test_weak_curvature_beside_a_free_direction_is_bounded(method, curvature):
    """P = diag(0, c) is singular, so the unboundedness certificate is allowed, yet the problem
    is bounded (x1 in a box, x2 = 1 / c): a direction whose curvature is large against P's
    own scale is no recession direction, however small against q'x."""
    Q = torch.diag(torch.tensor([0.0, curvature], dtype=F64))
    p = torch.tensor([-1.0, -1.0], dtype=F64)
    G = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=F64)
    h = torch.ones(2, dtype=F64)
    sol = solve_qp(Q, p, G, h, method=method)
    assert int(sol.status) == Status.SOLVED
    torch.testing.assert_close(sol.x, torch.tensor([1.0, 1.0 / curvature], dtype=F64))


def test_infeasible_box_and_equality_flagged():
    Q = torch.eye(3, dtype=F64).expand(4, 3, 3)
    p = torch.zeros(4, 3, dtype=F64)
    G = torch.ones(4, 1, 3, dtype=F64)
    h = torch.full((4, 1), -10.0, dtype=F64)  # sum(x) <= -10, impossible in the unit box
    lb = torch.zeros(3, dtype=F64)
    ub = torch.ones(3, dtype=F64)
    h[1] = 10.0  # feasible row
    A = torch.tensor([[[1.0, 0.0, 0.0]]], dtype=F64).expand(4, 1, 3)
    b = torch.tensor([[0.5], [0.5], [2.0], [0.5]], dtype=F64)  # row 2: x1 = 2 > ub
    sol = solve_qp(Q, p, G, h, A, b, lb, ub)
    assert sol.status.tolist() == [1, 0, 1, 1]
    assert (sol.x[[0, 2, 3]] == 0).all()
    torch.testing.assert_close(sol.x[1], torch.tensor([0.5, 0.0, 0.0], dtype=F64))


@pytest.mark.parametrize("method", ["auto", "enumerate", "ipm"])
def test_a_zero_equality_row_with_a_nonzero_right_side_is_infeasible(method):
    """``0'x = 1`` contradicts itself as ``0'x <= -1`` does: PRIMAL_INFEASIBLE with x = 0,
    its neighbours in the batch solved; ``0'x = 0`` constrains nothing."""
    Q = torch.eye(3, dtype=F64).expand(3, 3, 3)
    p = torch.tensor([-1.0, -1.0, 0.0], dtype=F64).expand(3, 3)
    A = torch.tensor([[[0.0, 0.0, 0.0]], [[1.0, -1.0, 0.0]], [[0.0, 0.0, 0.0]]], dtype=F64)
    b = torch.tensor([[1.0], [0.0], [0.0]], dtype=F64)
    G = torch.tensor([[1.0, 1.0, 1.0]], dtype=F64).expand(3, 1, 3)
    h = torch.full((3, 1), 1.0, dtype=F64)
    sol = solve_qp(Q, p, G, h, A, b, method=method)
    assert sol.status.tolist() == [Status.PRIMAL_INFEASIBLE, Status.SOLVED, Status.SOLVED]
    assert (sol.x[0] == 0).all()
    want = torch.tensor([[2.0, 2.0, -1.0]] * 2, dtype=F64) / 3  # x = (1, 1, 0) - (1, 1, 1) / 3
    torch.testing.assert_close(sol.x[1:], want)


def test_batch_equals_loop():
    batch = make_batch(12, 4, 6, 1, True, seed=11)
    args = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    full = solve_qp(*args)
    for i in range(12):
        one = solve_qp(*(t[i] for t in args))
        assert one.x.shape == (4,) and one.status.shape == ()
        assert int(one.status) == int(full.status[i])
        torch.testing.assert_close(one.x, full.x[i], atol=1e-7, rtol=0)
        torch.testing.assert_close(one.lam, full.lam[i], atol=1e-7, rtol=0)


def test_nonfinite_row_flagged_others_untouched():
    batch = make_batch(6, 3, 4, 0, True, seed=5, frac_infeasible=0.0)
    args = [batch.Q, batch.p, batch.G, batch.h, None, None, batch.lb, batch.ub]
    ref = solve_qp(*args)
    Q = batch.Q.clone()
    Q[1, 0, 0] = math.nan
    h = batch.h.clone()
    h[3, 2] = math.nan  # (+inf is "no bound": tests/qp/test_infinite_rows.py)
    lb = batch.lb.clone()
    lb[4, 0] = math.nan
    sol = solve_qp(Q, batch.p, batch.G, h, None, None, lb, batch.ub)
    assert sol.status.tolist() == [0, Status.NON_FINITE, 0, Status.NON_FINITE, Status.NON_FINITE, 0]
    for i in (1, 3, 4):
        assert (sol.x[i] == 0).all() and torch.isfinite(sol.lam[i]).all()
    for i in (0, 2, 5):
        torch.testing.assert_close(sol.x[i], ref.x[i])


def test_infinite_bounds_are_unbounded_components():
    Q = torch.eye(2, dtype=F64)
    p = torch.tensor([-3.0, 3.0], dtype=F64)
    lb = torch.tensor([-math.inf, -1.0], dtype=F64)
    ub = torch.tensor([1.0, math.inf], dtype=F64)
    sol = solve_qp(Q, p, lb=lb, ub=ub)
    torch.testing.assert_close(sol.x, torch.tensor([1.0, -1.0], dtype=F64))
    torch.testing.assert_close(sol.lam_ub, torch.tensor([2.0, 0.0], dtype=F64))
    torch.testing.assert_close(sol.lam_lb, torch.tensor([0.0, 2.0], dtype=F64))
    bad = solve_qp(Q, p, lb=torch.tensor([math.inf, 0.0], dtype=F64))
    assert int(bad.status) == Status.PRIMAL_INFEASIBLE


def test_broadcast_and_multi_batch_dims():
    batch = make_batch(6, 3, 2, 0, False, seed=2, frac_infeasible=0.0)
    sol = solve_qp(batch.Q[0], batch.p.view(2, 3, 3), batch.G[0], batch.h[0])
    assert sol.x.shape == (2, 3, 3) and sol.status.shape == (2, 3)
    loop = solve_qp(batch.Q[0].expand(6, 3, 3), batch.p, batch.G[0].expand(6, 2, 3), batch.h[0])
    torch.testing.assert_close(sol.x.reshape(6, 3), loop.x)
    one = solve_qp(batch.Q[:1], batch.p[:1], batch.G[:1], batch.h[:1])
    assert one.x.shape == (1, 3) and one.status.shape == (1,)


@pytest.mark.parametrize("method", ["auto", "active_set", "ipm"])
@pytest.mark.parametrize("name", ["Q", "p", "G", "h", "lb"])
def test_negated_views_are_read_as_their_values(method, name):
    """A tensor whose negative bit is set (``torch._neg_view``, or ``t.conj().imag`` of a
    complex tensor: its memory holds the values negated) gives the answer of its values on
    every method, the C kernels included."""
    batch = make_batch(5, 3, 4, 0, True, seed=7, frac_infeasible=0.0)
    args = dict(Q=batch.Q, p=batch.p, G=batch.G, h=batch.h, lb=batch.lb, ub=batch.ub)
    want = solve_qp(**args, method=method)
    args[name] = torch._neg_view(-args[name])
    assert args[name].is_neg()
    got = solve_qp(**args, method=method)
    torch.testing.assert_close(got.x, want.x, atol=0.0, rtol=0.0)
    torch.testing.assert_close(got.status, want.status)
    h = torch.complex(torch.zeros(1, 1, dtype=F64), torch.full((1, 1), -0.2, dtype=F64))
    G = torch.tensor([[[1.0, 0.0]]], dtype=F64)
    one = solve_qp(torch.eye(2, dtype=F64), -torch.ones(1, 2, dtype=F64), G, h.conj().imag,
                   method=method)  # fmt: skip
    torch.testing.assert_close(one.x, torch.tensor([[0.2, 1.0]], dtype=F64))


def test_closed_form_one_constraint(kernel):
    """Without the C kernel the closed form runs; with it (CPU) the dual method does."""
    g = torch.Generator().manual_seed(0)
    L = torch.randn(50, 3, 3, generator=g, dtype=F64)
    Q = L @ L.mT + torch.eye(3, dtype=F64)
    p = torch.randn(50, 3, generator=g, dtype=F64)
    G = torch.randn(50, 1, 3, generator=g, dtype=F64)
    h = torch.randn(50, 1, generator=g, dtype=F64)
    closed = solve_qp(Q, p, G, h)
    assert (closed.iterations == 0).all() != kernel  # the dual method counts its steps
    ipm = solve_qp(Q, p, G, h, lb=-math.inf, method="ipm")
    assert (ipm.iterations > 0).all()
    torch.testing.assert_close(closed.x, ipm.x, atol=1e-8, rtol=0)
    torch.testing.assert_close(closed.lam, ipm.lam, atol=1e-8, rtol=0)
    enum = solve_qp(Q, p, G, h, lb=-math.inf, method="enumerate")  # (infinite) bound rows
    assert (enum.iterations == 0).all()
    torch.testing.assert_close(closed.x, enum.x, atol=1e-10, rtol=0)
    torch.testing.assert_close(closed.lam, enum.lam, atol=1e-10, rtol=0)


def test_warm_start_and_options():
    batch = make_batch(8, 4, 6, 0, False, seed=9, frac_infeasible=0.0)
    args = (batch.Q, batch.p, batch.G, batch.h)
    cold = solve_qp(*args)
    warm = solve_qp(*args, warm_start=cold)
    torch.testing.assert_close(warm.x, cold.x, atol=1e-7, rtol=0)
    few = solve_qp(*args, max_iter=1, polish=False, method="ipm")
    assert (few.status == Status.MAX_ITER).any()
    assert torch.isfinite(few.x).all()


def test_errors_name_the_argument():
    Q = torch.eye(2, dtype=F64)
    p = torch.zeros(2, dtype=F64)
    G = torch.ones(1, 2, dtype=F64)
    h = torch.ones(1, dtype=F64)
    with pytest.raises(ValueError, match="Q must have shape"):
        solve_qp(torch.ones(2, 3, dtype=F64), p)
    with pytest.raises(ValueError, match="n >= 1"):
        solve_qp(torch.ones(0, 0, dtype=F64), torch.zeros(0, dtype=F64))
    with pytest.raises(ValueError, match="p must have shape"):
        solve_qp(Q, torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="h must have shape"):
        solve_qp(Q, p, G, torch.ones(2, dtype=F64))
    with pytest.raises(ValueError, match="G and h"):
        solve_qp(Q, p, G)
    with pytest.raises(TypeError, match="p has dtype"):
        solve_qp(Q, p.float())
    with pytest.raises(TypeError, match="Q must be float32 or float64"):
        solve_qp(torch.eye(2, dtype=torch.int64), p)
    with pytest.raises(TypeError, match="G must be a torch.Tensor"):
        solve_qp(Q, p, [[1.0, 1.0]], h)
    with pytest.raises(ValueError, match="batch dimensions"):
        solve_qp(Q.expand(3, 2, 2), p.expand(4, 2))
    with pytest.raises(ValueError, match="backend"):
        solve_qp(Q, p, backend="cvx")
    with pytest.raises(ValueError, match="soft"):
        solve_qp(Q, p, soft=torch.ones(1, dtype=F64))
    with pytest.raises(ValueError, match="lb must have shape"):
        solve_qp(Q, p, lb=torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="max_iter"):
        solve_qp(Q, p, max_iter=0)
    with pytest.raises(TypeError, match="polish"):
        solve_qp(Q, p, polish="yes")  # type: ignore[arg-type]


def test_solution_is_namedtuple():
    sol = solve_qp(torch.eye(2), torch.ones(2))
    assert isinstance(sol, QPSolution)
    assert sol._fields[:5] == ("x", "status", "lam", "nu", "iterations")
    torch.testing.assert_close(sol.x, -torch.ones(2))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cuda_matches_cpu(dtype):
    batch = make_batch(64, 4, 8, 1, True, seed=1, dtype=dtype)
    args = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    cpu = solve_qp(*args)
    gpu = solve_qp(*(t.cuda() for t in args))
    assert gpu.x.device.type == "cuda"
    assert torch.equal(gpu.status.cpu(), cpu.status)
    torch.testing.assert_close(gpu.x.cpu(), cpu.x, atol=TOL[dtype], rtol=0)


@pytest.mark.slow
def test_ten_thousand_vs_cvxpy(cvx):
    """10,000 random QPs over n in 2..12, m in 1..64 (reported figures in the issue note)."""
    shapes = TEN_THOUSAND_SHAPES
    per = 10_000 // len(shapes) + 1
    total = 0
    for k, (n, m, me, bd) in enumerate(shapes):
        for dtype in (torch.float64, torch.float32):
            batch = make_batch(per, n, m, me, bd, seed=1000 + k, dtype=dtype)
            sol = solve_qp(batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
            check_against_cvxpy(cvx, batch, sol, dtype, range(per))
        total += per
    assert total >= 10_000


def _c_compiler() -> str | None:
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    return shutil.which(cc)


@pytest.mark.skipif(_c_compiler() is None, reason="no C compiler: the kernel is optional")
def test_kernel_is_built_where_a_c_compiler_is_present():
    """``pip install`` compiles the kernel; its build is optional, so a broken build would
    otherwise only show as skipped kernel tests."""
    assert _dual_native.available(), "reinstall (pip install -e .) to build _dual_kernel.c"


@pytest.mark.parametrize("B", [1, 5])
@pytest.mark.parametrize("grad", [False, True])
def test_equality_constraints_alone(B: int, grad: bool) -> None:
    """No inequality rows and no bounds: the KKT system of the equalities, at every batch
    size, with and without gradients (against its linear solve and finite differences)."""
    g = torch.Generator().manual_seed(B)
    f64 = torch.float64
    L = torch.randn(B, 3, 3, generator=g, dtype=f64)
    Q = L @ L.mT + torch.eye(3, dtype=f64)
    p = torch.randn(B, 3, generator=g, dtype=f64).requires_grad_(grad)
    A = torch.randn(B, 1, 3, generator=g, dtype=f64)
    b = torch.randn(B, 1, generator=g, dtype=f64)
    sol = solve_qp(Q, p, A=A, b=b)
    K = torch.cat(
        [torch.cat([Q, A.mT], -1), torch.cat([A, torch.zeros(B, 1, 1, dtype=f64)], -1)], -2
    )
    want = torch.linalg.solve(K, torch.cat([-p.detach(), b], -1))
    assert (sol.status == 0).all()
    torch.testing.assert_close(sol.x.detach(), want[:, :3], atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(sol.nu.detach(), want[:, 3:], atol=1e-9, rtol=1e-9)
    if grad:
        sol.x.sum().backward()
        dx_dp = torch.linalg.solve(
            K, torch.cat([-torch.ones(B, 3, dtype=f64), torch.zeros(B, 1, dtype=f64)], -1)
        )
        torch.testing.assert_close(p.grad, dx_dp[:, :3], atol=1e-9, rtol=1e-9)


def test_a_diverging_last_iterate_stays_finite_in_float32() -> None:
    """A float32 LP whose equalities fix ``x`` where one row is violated by rounding alone:
    not SOLVED, and every output finite (the float64 iterate reaches 1e53)."""
    t = lambda rows: torch.tensor(rows, dtype=torch.float32)  # noqa: E731
    p = t([-0.15712, -2.11132, -0.73333, -0.36815])
    G = t([[-0.17358209, 0.77721763, -0.01454346, 1.60137808],
           [0.63277680, 0.59003025, 1.02774477, 0.49774244],
           [0.33232301, -0.55805767, -0.35314232, 0.37488523],
           [-0.09961575, 0.29993618, 0.23115881, -0.18528463]])  # fmt: skip
    h = t([-0.1788944006, 0.8543500304, 0.4622353315, 0.1784370393])
    A = t([[1.36802411, -0.45046702, -0.02873789, 0.38856354],
           [1.23441339, -1.97315657, 0.36609548, 1.43809950],
           [-0.21949653, 1.09724844, -0.09881322, -1.64447427],
           [-0.19473398, 0.97503000, 0.16447799, -0.23382339]])  # fmt: skip
    b = t([-0.5710104108, -1.2860493660, 0.8510959744, 0.4178529084])
    sol = solve_qp(torch.zeros(4, 4), p, G, h, A, b, lb=torch.full((4,), -2.4605),
                   ub=torch.full((4,), 2.97974))  # fmt: skip
    assert int(sol.status) != Status.SOLVED
    for field in (sol.x, sol.lam, sol.nu, sol.lam_lb, sol.lam_ub):
        assert torch.isfinite(field).all()
