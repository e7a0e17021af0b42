"""Equality rows eliminated by a null-space basis (``method="auto"`` on the CPU with the C
kernel): answers, multipliers and statuses against Clarabel, one problem at a time against
the batch, gradients against finite differences, and the rows the elimination leaves."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _problems import make_batch

from torchcbf.qp import Status, _dual_native, _eliminate, solve_qp

F64 = torch.float64
TOL = {torch.float64: 1e-7, torch.float32: 2e-4}

pytestmark = pytest.mark.skipif(not _dual_native.available(), reason="needs the C kernel")


def _kkt_residual(data, sol) -> torch.Tensor:
    """Largest stationarity residual ``Qx + p + G'lam + A'nu - lam_lb + lam_ub`` per row."""
    Q, p, G, h, A, b = (t.double() for t in data[:6])
    r = (
        torch.einsum("...ij,...j->...i", Q, sol.x.double())
        + p
        + torch.einsum("...mn,...m->...n", G, sol.lam.double())
        + torch.einsum("...kn,...k->...n", A, sol.nu.double())
        - sol.lam_lb.double()
        + sol.lam_ub.double()
    )
    return r.abs().amax(-1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("B", [1, 5, 40])
@pytest.mark.parametrize("shape", [(4, 6, 2, True), (10, 8, 3, False), (12, 20, 5, True)])
def test_matches_clarabel(cvx, shape, B, dtype):
    n, m, k, bounds = shape
    batch = make_batch(B, n, m, k, bounds, seed=11 * n + B, dtype=dtype)
    data = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    with torch.no_grad():
        sol = solve_qp(*data)
    # a few problems, all solved: the real-time path; otherwise (and for a batch) the general one
    all_solved = all(kind != "infeasible" for kind in batch.kind)
    assert sol.path == ("small_native" if B <= 16 and all_solved else "active_set_native")
    tol = TOL[dtype]
    res = _kkt_residual(data, sol)
    for i in range(B):
        ref, obj, status = cvx(*(None if t is None else t[i].double().numpy() for t in data))
        if batch.kind[i] == "infeasible":
            assert status == "infeasible" and int(sol.status[i]) == Status.PRIMAL_INFEASIBLE
            assert float(sol.x[i].abs().max()) == 0.0
            continue
        assert status == "optimal" and int(sol.status[i]) == Status.SOLVED, (i, batch.kind[i])
        x = sol.x[i].double().numpy()
        assert np.abs(x - ref).max() <= tol * (1.0 + np.abs(ref).max())
        assert float(res[i]) <= 100 * tol * (1.0 + float(sol.lam[i].abs().max()))


def test_a_problem_alone_equals_it_in_a_batch():
    batch = make_batch(24, 6, 7, 2, True, seed=5)
    data = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, batch.lb, batch.ub)
    with torch.no_grad():
        full = solve_qp(*data)
        assert full.path == "active_set_native"
        for i in range(0, 24, 5):
            one = solve_qp(*(t[i] for t in data))
            alone = "small_native" if batch.kind[i] != "infeasible" else "active_set_native"
            assert one.path == alone and int(one.status) == int(full.status[i])
            for name in ("x", "lam", "nu", "lam_lb", "lam_ub"):
                torch.testing.assert_close(
                    getattr(one, name), getattr(full, name)[i], atol=1e-9, rtol=0
                )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradients_match_finite_differences(dtype):
    batch = make_batch(3, 5, 4, 2, False, seed=2, frac_infeasible=0.0, frac_inactive=0.0)
    base = [t.double() for t in (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b)]
    weights = torch.linspace(-1.0, 2.0, 5, dtype=F64)

    def loss(*args):
        sol = solve_qp(*args)
        assert bool((sol.status == Status.SOLVED).all())
        return (sol.x * weights.to(sol.x.dtype)).sum() + sol.nu.sum()

    inputs = [t.to(dtype).requires_grad_() for t in base]
    grads = torch.autograd.grad(loss(*inputs), inputs)
    step = 1e-6
    for j, name in enumerate(("Q", "p", "G", "h", "A", "b")):
        t = base[j]
        fd = torch.zeros_like(t)
        flat = fd.view(-1)
        for e in range(t.numel()):
            hi, lo = [u.clone() for u in base], [u.clone() for u in base]
            hi[j].view(-1)[e] += step
            lo[j].view(-1)[e] -= step
            with torch.no_grad():
                flat[e] = (loss(*hi) - loss(*lo)) / (2 * step)
        if name == "Q":  # the solver symmetrises Q, so compare symmetric parts
            fd = 0.5 * (fd + fd.mT)
            g = 0.5 * (grads[j] + grads[j].mT).double()
        else:
            g = grads[j].double()
        tol = 1e-5 if dtype == F64 else 2e-2
        torch.testing.assert_close(g, fd, atol=tol, rtol=tol, msg=name)


def test_gradcheck_through_the_eliminated_path():
    batch = make_batch(2, 4, 3, 1, False, seed=9, frac_infeasible=0.0, frac_inactive=0.0)
    args = [t.clone().requires_grad_() for t in (batch.p, batch.h, batch.A, batch.b)]

    def fn(p, h, A, b):
        sol = solve_qp(batch.Q, p, batch.G, h, A, b)
        assert sol.path == "active_set_native"
        return sol.x, sol.nu

    assert torch.autograd.gradcheck(fn, args, atol=1e-6, rtol=1e-5)


def test_dependent_equalities_take_the_general_path(cvx):
    """Repeated and combined rows of ``A`` (consistent): not eliminated, still solved."""
    batch = make_batch(20, 6, 5, 2, False, seed=3, frac_infeasible=0.0)
    A = torch.cat((batch.A, batch.A[:, :1] + 2.0 * batch.A[:, 1:2]), 1)
    b = torch.cat((batch.b, batch.b[:, :1] + 2.0 * batch.b[:, 1:2]), 1)
    A[:10], b[:10] = A[:10, [0, 1, 1]], b[:10, [0, 1, 1]]
    red = _eliminate.reduce_equalities(A, b)
    assert not bool(red.ok.any())
    data = (batch.Q, batch.p, batch.G, batch.h, A, b)
    for B in (1, 20):
        with torch.no_grad():
            sol = solve_qp(*(t[:B] for t in data))
        for i in range(B):
            ref, _, status = cvx(*(t[i].numpy() for t in data))
            assert status == "optimal" and int(sol.status[i]) == Status.SOLVED
            assert np.abs(sol.x[i].numpy() - ref).max() <= 1e-7 * (1 + np.abs(ref).max())


@pytest.mark.parametrize("B", [1, 20])
def test_dependent_equalities_of_any_scale_are_judged_on_unit_rows(cvx, B):
    """``a x = b`` repeated as ``1e12 a x = 1e12 (b + 1)`` contradicts it (infeasible, not a
    solved row that misses the first by about 1); ``1e12 a x = 1e12 b`` repeats it (solved,
    its multipliers stationary)."""
    batch = make_batch(B, 5, 6, 2, False, seed=5, frac_infeasible=0.0)
    first = batch.A[:, :1]
    A = torch.cat((batch.A, 1e12 * first), 1)
    for shift, want in ((1.0, Status.PRIMAL_INFEASIBLE), (0.0, Status.SOLVED)):
        b = torch.cat((batch.b, 1e12 * (batch.b[:, :1] + shift)), 1)
        data = (batch.Q, batch.p, batch.G, batch.h, A, b)
        with torch.no_grad():
            sol = solve_qp(*data)
        assert sol.status.tolist() == [want] * B, shift
        if want == Status.SOLVED:
            for i in range(min(B, 3)):
                ref, _, _ = cvx(*(t[i].numpy() for t in data[:4]), batch.A[i].numpy(),
                                batch.b[i].numpy())  # fmt: skip
                assert np.abs(sol.x[i].numpy() - ref).max() <= 1e-7 * (1 + np.abs(ref).max())
            assert float(_kkt_residual(data, sol).max()) < 1e-8


def test_a_batch_mixing_dependent_and_independent_equalities(cvx):
    batch = make_batch(30, 5, 6, 2, True, seed=8, frac_infeasible=0.0)
    A, b = batch.A.clone(), batch.b.clone()
    A[::3, 1], b[::3, 1] = 3.0 * A[::3, 0], 3.0 * b[::3, 0]
    data = (batch.Q, batch.p, batch.G, batch.h, A, b, batch.lb, batch.ub)
    p = batch.p.clone().requires_grad_()
    sol = solve_qp(batch.Q, p, *data[2:])
    assert bool((sol.status == Status.SOLVED).all())
    (g,) = torch.autograd.grad(sol.x.sum(), p)
    assert bool(torch.isfinite(g).all())
    for i in (0, 1, 3, 4):
        ref, _, _ = cvx(*(t[i].detach().numpy() for t in data))
        assert np.abs(sol.x[i].detach().numpy() - ref).max() <= 1e-7 * (1 + np.abs(ref).max())
    assert float(_kkt_residual(data, sol).detach().max()) < 1e-9


@pytest.mark.parametrize("B", [1, 20])
def test_rows_in_the_span_of_the_equalities(B):
    """``x1 + x2 = 1`` with ``2 x1 + 2 x2 <= c``: implied for ``c >= 2``, contradicted below."""
    Q = torch.eye(3, dtype=F64).expand(B, 3, 3)
    p = torch.tensor([1.0, -1.0, 0.5], dtype=F64).expand(B, 3)
    G = torch.tensor([[2.0, 2.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64).expand(B, 2, 3)
    A = torch.tensor([[1.0, 1.0, 0.0]], dtype=F64).expand(B, 1, 3)
    b = torch.ones(B, 1, dtype=F64)
    with torch.no_grad():
        for c, expect in (
            (2.0, Status.SOLVED),
            (3.0, Status.SOLVED),
            (1.9, Status.PRIMAL_INFEASIBLE),
        ):
            h = torch.tensor([c, 0.0], dtype=F64).expand(B, 2)
            sol = solve_qp(Q, p, G, h, A, b)
            assert bool((sol.status == expect).all()), (c, sol.status)
            if expect == Status.SOLVED:
                x = torch.tensor([-0.5, 1.5, -0.5], dtype=F64).expand(B, 3)
                torch.testing.assert_close(sol.x, x, atol=1e-12, rtol=0)


def test_infinite_rows_and_bounds_with_equalities():
    Q = torch.eye(3, dtype=F64)
    p = -torch.ones(3, dtype=F64)
    G = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0]], dtype=F64)
    h = torch.tensor([1.0, torch.inf], dtype=F64)
    A = torch.tensor([[1.0, -1.0, 0.0]], dtype=F64)
    b = torch.zeros(1, dtype=F64)
    lb = torch.tensor([-torch.inf, -torch.inf, 0.5], dtype=F64)
    ub = torch.full((3,), torch.inf, dtype=F64)
    for batch in ((), (20,)):
        args = [t.expand(*batch, *t.shape) for t in (Q, p, G, h, A, b, lb, ub)]
        with torch.no_grad():
            sol = solve_qp(*args)
        assert bool((sol.status == Status.SOLVED).all())
        x = torch.tensor([0.25, 0.25, 0.5], dtype=F64).expand(*batch, 3)
        torch.testing.assert_close(sol.x, x, atol=1e-12, rtol=0)
        assert float(sol.lam[..., 1].abs().max()) == 0.0
        assert float(sol.lam_ub.abs().max()) == 0.0
        assert float(_kkt_residual(args, sol).max()) < 1e-12


def test_unbounded_reduced_problem_is_certified():
    """No curvature along ``x3`` within ``x1 = x2``, which the objective rewards."""
    Q = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    p = torch.tensor([0.0, 0.0, -1.0], dtype=F64)
    G = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64)
    h = torch.ones(1, dtype=F64)
    A = torch.tensor([[1.0, -1.0, 0.0]], dtype=F64)
    b = torch.zeros(1, dtype=F64)
    for batch in ((), (20,)):
        args = [t.expand(*batch, *t.shape) for t in (Q, p, G, h, A, b)]
        with torch.no_grad():
            sol = solve_qp(*args)
        assert bool((sol.status == Status.DUAL_INFEASIBLE).all())


@pytest.mark.parametrize("which", ["lb", "ub"])
@pytest.mark.parametrize("B", [1, 3, 20])
def test_one_sided_bounds_with_equalities(cvx, which, B):
    batch = make_batch(B, 6, 4, 2, True, seed=B, frac_infeasible=0.0)
    lb = batch.lb if which == "lb" else None
    ub = batch.ub if which == "ub" else None
    data = (batch.Q, batch.p, batch.G, batch.h, batch.A, batch.b, lb, ub)
    with torch.no_grad():
        sol = solve_qp(*data)
    assert bool((sol.status == Status.SOLVED).all())
    res = _kkt_residual(data, sol)
    assert float(res.max()) < 1e-9
    absent = sol.lam_ub if which == "lb" else sol.lam_lb
    assert float(absent.abs().max()) == 0.0
    for i in range(B):
        row = [None if t is None else t[i].numpy() for t in data]
        ref, _, status = cvx(*row)
        assert status == "optimal"
        assert np.abs(sol.x[i].numpy() - ref).max() <= 1e-7 * (1.0 + np.abs(ref).max())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("B", [1, 4])
def test_the_kernels_elimination_equals_the_torch_elimination(dtype, B):
    """A few problems without gradients are eliminated in the C kernel, with gradients by
    the torch elimination of the general path: the same statuses, answers and multipliers
    (rows with ``h = +inf``, one-sided and two-sided bounds included)."""
    g = torch.Generator().manual_seed(11 + B)
    n, m, k = 9, 7, 3
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = (G @ x0.unsqueeze(-1)).squeeze(-1) + 0.1 * torch.rand(B, m, generator=g, dtype=F64)
    h[:, 2] = torch.inf
    A = torch.randn(B, k, n, generator=g, dtype=F64)
    b = (A @ x0.unsqueeze(-1)).squeeze(-1)
    lb = torch.full((n,), -1.5, dtype=F64)
    lb[1] = -torch.inf
    ub = torch.full((n,), 1.5, dtype=F64)
    ub[4] = torch.inf
    lb, ub = torch.minimum(lb, x0.amin(0)), torch.maximum(ub, x0.amax(0))
    data = [t.to(dtype) for t in (Q, p, G, h, A, b, lb, ub)]
    with torch.no_grad():
        fast = solve_qp(*data[:6], lb=data[6], ub=data[7])
    general = solve_qp(data[0], data[1].clone().requires_grad_(), *data[2:6], lb=data[6],
                       ub=data[7])  # fmt: skip
    assert fast.path == "small_native" and general.path == "active_set_native"
    assert torch.equal(fast.status, general.status)
    assert bool((fast.status == Status.SOLVED).all())
    tol = 1e-9 if dtype == F64 else 1e-4
    for name in ("x", "lam", "nu", "lam_lb", "lam_ub"):
        a, c = getattr(fast, name).double(), getattr(general, name).detach().double()
        assert float((a - c).abs().max()) <= tol * (1 + float(c.abs().max())), name
    assert float((fast.lam[:, 2]).abs().max()) == 0.0
