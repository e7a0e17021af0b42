"""Rows without a bound: ``h = +inf``, ``lb = -inf`` and ``ub = +inf`` are ignored by every
method and path (the answer is that of the problem without them), ``h = -inf`` is
infeasible and NaN stays non-finite; gradients flow through a problem with such rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcbf.qp import Status, solve_qp

METHODS = ("auto", "active_set", "enumerate", "ipm")
DTYPES = (torch.float64, torch.float32)


def _problem(B: int, n: int = 3, m: int = 5, seed: int = 0):
    """``B`` strictly convex QPs whose rows ``1`` and (on every third problem) ``3`` have
    ``h = +inf``; ``x = 0`` is feasible for the finite rows. Box with infinite entries."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    R = torch.randn(B, n, n, generator=g, dtype=f64)
    Q = R @ R.mT / n + 0.5 * torch.eye(n, dtype=f64)
    p = 3 * torch.randn(B, n, generator=g, dtype=f64)
    G = torch.randn(B, m, n, generator=g, dtype=f64)
    h = torch.rand(B, m, generator=g, dtype=f64) + 0.1
    h[:, 1] = math.inf
    h[::3, 3] = math.inf
    lb = torch.full((B, n), -1.5, dtype=f64)
    ub = torch.full((B, n), 1.5, dtype=f64)
    lb[:, 0] = -math.inf
    ub[:, 1] = math.inf
    return Q, p, G, h, lb, ub


def _reference(cvx, Q, p, G, h, lb, ub) -> np.ndarray:
    """Clarabel's minimiser of each problem with its infinite rows dropped."""
    out = []
    for i in range(len(p)):
        keep = np.isfinite(h[i].numpy())
        x, _, status = cvx(Q[i].numpy(), p[i].numpy(), G[i].numpy()[keep], h[i].numpy()[keep],
                           lb=lb[i].numpy(), ub=ub[i].numpy())  # fmt: skip
        assert status == "optimal"
        out.append(x)
    return np.stack(out)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("B", [1, 5, 40], ids=["B1", "B5", "B40"])
def test_infinite_rows_are_ignored(cvx, method, dtype, B):
    Q, p, G, h, lb, ub = _problem(B)
    ref = _reference(cvx, Q, p, G, h, lb, ub)
    args = [t.to(dtype) for t in (Q, p, G, h, lb, ub)]
    sol = solve_qp(*args[:4], lb=args[4], ub=args[5], method=method)
    assert (sol.status == int(Status.SOLVED)).all(), sol.status
    tol = 1e-6 if dtype == torch.float64 else 2e-3
    ref_t = torch.from_numpy(ref)
    err = (sol.x.double() - ref_t).abs().amax(-1) / (1 + ref_t.abs().amax(-1))
    assert float(err.max()) <= tol
    assert (sol.lam[~torch.isfinite(args[3])] == 0).all()
    assert (sol.lam_lb[:, 0] == 0).all() and (sol.lam_ub[:, 1] == 0).all()
    # one problem without a batch dimension answers as its row of the batch
    one = solve_qp(*(t[0] for t in args[:4]), lb=args[4][0], ub=args[5][0], method=method)
    assert int(one.status) == int(Status.SOLVED)
    assert float((one.x.double() - torch.from_numpy(ref[0])).abs().max()) <= tol * (
        1 + float(np.abs(ref[0]).max())
    )


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
def test_small_batch_c_path_takes_infinite_rows(dtype):
    """A few rows without gradients go to the C kernel's real-time entry (where it was
    built) even with ``h = +inf`` rows, and answer as the general path."""
    from torchcbf.qp import realtime

    Q, p, G, h, lb, ub = (t.to(dtype) for t in _problem(5))
    small = solve_qp(Q, p, G, h, lb=lb, ub=ub)
    general = solve_qp(Q, p, G, h, lb=lb, ub=ub, method="enumerate")
    if realtime.available():
        assert small.path == "small_native"
    assert (small.status == 0).all() and (general.status == 0).all()
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(small.x, general.x, atol=tol, rtol=tol)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("B", [3, 40])
def test_nan_and_minus_inf_rows(method, B):
    Q, p, G, h, lb, ub = _problem(B)
    h[0, 0] = math.nan
    h[1, 2] = -math.inf
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    assert int(sol.status[0]) == int(Status.NON_FINITE)
    assert int(sol.status[1]) == int(Status.PRIMAL_INFEASIBLE)
    assert (sol.status[2:] == int(Status.SOLVED)).all()
    assert (sol.x[:2] == 0).all()


def test_nan_in_the_row_of_an_infinite_h_stays_non_finite():
    Q, p, G, h, lb, ub = _problem(4)
    G[2, 1, 0] = math.nan  # row 1 has h = +inf
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub)
    assert int(sol.status[2]) == int(Status.NON_FINITE)
    assert (sol.status[[0, 1, 3]] == int(Status.SOLVED)).all()


@pytest.mark.parametrize("method", METHODS)
def test_soft_rows_with_infinite_h(cvx, method):
    Q, p, G, h, lb, ub = _problem(6)
    soft = torch.full_like(h, 10.0)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, soft=soft, method=method)
    assert (sol.status == 0).all()
    assert (sol.slack[~torch.isfinite(h)] == 0).all()
    hard = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    # x = 0 is feasible and the penalty is exact: no slack is used
    torch.testing.assert_close(sol.x, hard.x, atol=1e-6, rtol=1e-6)


# the interior point's gradcheck takes 9 s: in the slow suite
SLOW_IPM = pytest.param("ipm", marks=pytest.mark.slow)


@pytest.mark.parametrize("method", ["auto", "enumerate", SLOW_IPM])
def test_gradcheck_through_infinite_rows(method):
    Q, p, G, h, lb, ub = _problem(3, seed=1)
    # make the finite rows bind: a large linear term pushes x against them
    p = 4 * p
    Q, p, G, h = (t.clone().requires_grad_(True) for t in (Q, p, G, h))

    def f(Q, p, G, h):
        return solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method).x

    assert (solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method).status == 0).all()
    assert torch.autograd.gradcheck(f, (Q, p, G, h), eps=1e-6, atol=1e-5, rtol=1e-4)
    x = f(Q, p, G, h)
    x.sum().backward()
    assert torch.isfinite(G.grad).all() and torch.isfinite(h.grad).all()
    assert (G.grad[:, 1] == 0).all() and (h.grad[:, 1] == 0).all()


@pytest.mark.parametrize("method", ["auto", "active_set"])
def test_infinite_rows_with_and_without_the_kernel(cvx, kernel, method):
    Q, p, G, h, lb, ub = _problem(20, seed=2)
    ref = torch.from_numpy(_reference(cvx, Q, p, G, h, lb, ub))
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    assert (sol.status == 0).all()
    assert float((sol.x - ref).abs().max()) <= 1e-6 * (1 + float(ref.abs().max()))
