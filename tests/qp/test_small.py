"""The real-time path for a few small QPs without gradients (one call of the C kernel):
same answers as the general path and as cvxpy, and the general path wherever it does not
certify a row."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, _dual_native, realtime, solve_qp

pytestmark = pytest.mark.skipif(not _dual_native.available(), reason="C kernel not built")


def _general(*args, **kwargs):
    """The same solve through the general path (an input that requires grad skips the
    small path)."""
    Q = args[0].detach().requires_grad_()
    sol = solve_qp(Q, *args[1:], **kwargs)
    assert sol.path != "small_native", sol.path
    return sol


def _fields_close(a, b, tol):
    for name in ("x", "lam", "nu", "lam_lb", "lam_ub", "slack"):
        va, vb = getattr(a, name), getattr(b, name).detach()
        assert va.shape == vb.shape, name
        assert va.dtype == vb.dtype, name
        torch.testing.assert_close(va, vb, atol=tol, rtol=tol, msg=name)
    assert torch.equal(a.status, b.status)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("bounds", [False, True])
def test_small_path_matches_general_path_and_cvxpy(cvx, dtype, bounds):
    batch = make_batch(5, 3, 6, bounds=bounds, seed=3, frac_infeasible=0.0)
    args = [t.to(dtype) for t in (batch.Q, batch.p, batch.G, batch.h)]
    kw = {}
    if bounds:
        kw = {"lb": batch.lb.to(dtype), "ub": batch.ub.to(dtype)}
    with torch.no_grad():
        small = solve_qp(*args, **kw)
    assert small.path == "small_native"
    general = _general(*args, **kw)
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    _fields_close(small, general, tol)
    for i in range(5):
        ref, _, st = cvx(
            *(t[i].double().numpy() for t in (batch.Q, batch.p, batch.G, batch.h)),
            lb=None if not bounds else batch.lb[i].numpy(),
            ub=None if not bounds else batch.ub[i].numpy(),
        )
        assert st == "optimal"
        err = np.abs(small.x[i].double().numpy() - ref).max()
        assert err < (1e-7 if dtype == torch.float64 else 1e-3)


def test_one_qp_without_batch_dims_and_infinite_bounds(cvx):
    g = torch.Generator().manual_seed(1)
    Q = torch.eye(2, dtype=torch.float64)
    p = 3 * torch.randn(2, generator=g, dtype=torch.float64)
    G = torch.randn(6, 2, generator=g, dtype=torch.float64)
    h = 0.2 + torch.rand(6, generator=g, dtype=torch.float64)
    lb = torch.tensor([-0.3, -torch.inf], dtype=torch.float64)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h, lb=lb, ub=torch.inf)
    assert sol.path == "small_native"
    assert sol.x.shape == (2,) and sol.status.shape == () and sol.nu.shape == (0,)
    ref, _, _ = cvx(Q.numpy(), p.numpy(), G.numpy(), h.numpy(), lb=lb.numpy())
    assert np.abs(sol.x.numpy() - ref).max() < 1e-7
    assert float(sol.lam_ub.abs().max()) == 0.0
    _fields_close(sol, _general(Q, p, G, h, lb=lb, ub=torch.inf), 1e-10)


def test_rows_the_kernel_does_not_certify_take_the_general_path():
    good = make_batch(3, 3, 6, seed=5, frac_infeasible=0.0)
    bad = make_batch(3, 3, 6, seed=6, frac_infeasible=1.0)
    Q, p, G, h = (torch.cat((getattr(good, k), getattr(bad, k))) for k in ("Q", "p", "G", "h"))
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    assert sol.path != "small_native", sol.path
    general = _general(Q, p, G, h)
    _fields_close(sol, general, 1e-10)
    assert sol.status.tolist() == [Status.SOLVED] * 3 + [Status.PRIMAL_INFEASIBLE] * 3


def test_non_finite_and_empty_bound_rows_take_the_general_path():
    Q = torch.eye(2, dtype=torch.float64).repeat(2, 1, 1)
    p = torch.tensor([[1.0, 0.0], [float("nan"), 0.0]], dtype=torch.float64)
    G = torch.ones(2, 1, 2, dtype=torch.float64)
    h = torch.ones(2, 1, dtype=torch.float64)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
        empty = solve_qp(Q[0], p[0], G[0], h[0], lb=torch.inf)
    assert sol.path != "small_native" and empty.path != "small_native", (sol.path, empty.path)
    assert sol.status.tolist() == [Status.SOLVED, Status.NON_FINITE]
    assert int(empty.status) == Status.PRIMAL_INFEASIBLE


def test_solve_small_returns_none_where_it_does_not_apply():
    P = torch.eye(65, dtype=torch.float64)[None]
    q = torch.ones(1, 65, dtype=torch.float64)
    G = torch.ones(1, 1, 65, dtype=torch.float64)
    h = torch.ones(1, 1, dtype=torch.float64)
    assert realtime.solve_small(P, q, G, h, None, None, 1e-7, 50, (1,)) is None  # 65 variables
    assert (
        realtime.solve_small(P[:, :2, :2], q[:, :2], None, None, None, None, 1e-7, 50, (1,)) is None
    )


def test_ill_conditioned_row_takes_the_general_path(cvx):
    """One row with a rotated Q of condition 1e9 among well-conditioned ones: the kernel
    declines the batch, the general path answers it, and every row matches cvxpy."""
    batch = make_batch(3, 3, 6, seed=11, frac_infeasible=0.0)
    Q, p, G, h = batch.Q.clone(), batch.p, batch.G, batch.h
    rot, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(2),
                                         dtype=torch.float64))  # fmt: skip
    Q[1] = rot @ torch.diag(torch.tensor([1.0, 1e-4, 1e-9], dtype=torch.float64)) @ rot.T
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
        well = solve_qp(Q[[0, 2]], p[[0, 2]], G[[0, 2]], h[[0, 2]])
    assert sol.path != "small_native" and well.path == "small_native", (sol.path, well.path)
    _fields_close(sol, _general(Q, p, G, h), 1e-9)
    for i in range(3):
        ref, _, st = cvx(*(t[i].numpy() for t in (Q, p, G, h)))
        assert st == "optimal"
        scale = 1.0 + np.abs(ref).max()
        assert np.abs(sol.x[i].numpy() - ref).max() < 1e-6 * scale
    assert torch.equal(well.status, torch.zeros(2, dtype=torch.int64))
