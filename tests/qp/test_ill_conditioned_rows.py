"""Rows whose ``Q`` is too ill-conditioned for the dual method's own answer (rotated, condition
1e5 to 1e9) in a batch of easy ones: certified as KKT points to rounding by an active-set solve
or by enumeration on each candidate's KKT system, without the interior point method's
iterations; answers against Clarabel, alone and in the batch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcbf.qp import Status, _dual_native, solve_qp
from torchcbf.qp import _function as qp_function

F64 = torch.float64


def _batch(B: int, cond: float, hard_rows: tuple[int, ...], seed: int = 3):
    g = torch.Generator().manual_seed(seed)
    n, m = 4, 8
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = 0.2 + torch.rand(B, m, generator=g, dtype=F64)
    for i in hard_rows:
        rot, _ = torch.linalg.qr(torch.randn(n, n, generator=g, dtype=F64))
        eig = torch.logspace(0, -np.log10(cond), n, dtype=F64)
        Q[i] = rot @ torch.diag(eig) @ rot.T
    return Q, p, G, h


def _no_interior_point(*args, **kwargs):
    raise AssertionError("the interior point method ran")


@pytest.mark.parametrize("cond", [1e5, 1e7, 1e9])
@pytest.mark.parametrize("B", [1, 64])
def test_hard_rows_certified_without_the_interior_point_method(cvx, monkeypatch, cond, B):
    hard = (0,) if B == 1 else (5, 32, 40)
    Q, p, G, h = _batch(B, cond, hard)
    monkeypatch.setattr(qp_function, "solve_ipm", _no_interior_point)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    monkeypatch.undo()
    assert bool((sol.status == Status.SOLVED).all())
    for i in hard:
        ref, _, status = cvx(Q[i].numpy(), p[i].numpy(), G[i].numpy(), h[i].numpy())
        assert status == "optimal"
        assert np.abs(sol.x[i].numpy() - ref).max() <= 1e-6 * (1 + np.abs(ref).max())
        alone = solve_qp(Q[i], p[i], G[i], h[i])
        assert int(alone.status) == Status.SOLVED
        torch.testing.assert_close(alone.x, sol.x[i], atol=1e-9 * (1 + float(alone.x.abs().max())),
                                   rtol=0)  # fmt: skip


def test_hard_rows_in_float32_and_with_gradients(cvx):
    Q, p, G, h = _batch(64, 1e9, (7, 50))
    sol = solve_qp(Q.float(), p.float(), G.float(), h.float())
    assert bool((sol.status == Status.SOLVED).all())
    for i in (7, 50):
        ref, _, _ = cvx(Q[i].numpy(), p[i].numpy(), G[i].numpy(), h[i].numpy())
        assert np.abs(sol.x[i].double().numpy() - ref).max() <= 1e-3 * (1 + np.abs(ref).max())
    pg = p.clone().requires_grad_()
    out = solve_qp(Q, pg, G, h)
    assert bool((out.status == Status.SOLVED).all())
    (grad,) = torch.autograd.grad(out.x.sum(), pg)
    assert bool(torch.isfinite(grad).all())
    # the gradient of a hard row against central differences in its own p
    i, step = 7, 1e-6
    for j in range(4):
        hi, lo = p.clone(), p.clone()
        hi[i, j] += step
        lo[i, j] -= step
        fd = (solve_qp(Q[i], hi[i], G[i], h[i]).x - solve_qp(Q[i], lo[i], G[i], h[i]).x).sum()
        assert abs(float(fd) / (2 * step) - float(grad[i, j])) <= 1e-4 * (
            1 + abs(float(grad[i, j]))
        )


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_kernel_certification_agrees_with_the_torch_certification(cvx, monkeypatch, dtype):
    """The C kernel certifies the hard rows of a float64 batch itself (the torch steps do not
    run); its statuses equal those of the torch certification and both answers match
    Clarabel."""
    if not _dual_native.can_certify():
        pytest.skip("the C kernel of the dual method was not built")
    hard = (3, 17, 18, 40)
    Q, p, G, h = (t.to(dtype) for t in _batch(48, 1e8, hard, seed=5))
    torch_steps = qp_function._kkt.solve_active
    with torch.no_grad():
        monkeypatch.setattr(_dual_native, "can_certify", lambda: False)
        ref = solve_qp(Q, p, G, h)
        monkeypatch.undo()
        if dtype == F64:
            # in float32 such a P is singular to the inputs' rounding: the torch steps decide
            # whether a point is a direction of unbounded descent
            monkeypatch.setattr(qp_function._kkt, "solve_active", _no_interior_point)
        monkeypatch.setattr(qp_function, "solve_ipm", _no_interior_point)
        sol = solve_qp(Q, p, G, h)
        monkeypatch.undo()
    assert qp_function._kkt.solve_active is torch_steps
    assert torch.equal(sol.status, ref.status)
    assert bool((sol.status == Status.SOLVED).all())
    assert sol.method_names() == ["active_set"] * 48
    tol = 1e-6 if dtype == F64 else 2e-4
    for i in hard:
        Qi, pi, Gi, hi = (t[i].double().numpy() for t in (Q, p, G, h))
        x_ref, _, status = cvx(Qi, pi, Gi, hi)
        assert status == "optimal"
        scale = 1 + np.abs(x_ref).max()
        assert np.abs(sol.x[i].double().numpy() - x_ref).max() <= tol * scale
        assert np.abs(ref.x[i].double().numpy() - x_ref).max() <= tol * scale


def test_rows_the_kernel_leaves_take_the_torch_certification(monkeypatch):
    """A row the kernel cannot certify (it returns uncertified) is certified by the torch
    steps, with the answer it would have had without the kernel."""
    if not _dual_native.can_certify():
        pytest.skip("the C kernel of the dual method was not built")
    Q, p, G, h = _batch(16, 1e9, (2, 9), seed=6)
    real = _dual_native.certify

    def leaves_row_9(*args, **kwargs):
        x, z, done = real(*args, **kwargs)
        done = done.clone()
        done[9] = False
        return x, z, done

    with torch.no_grad():
        monkeypatch.setattr(_dual_native, "can_certify", lambda: False)
        ref = solve_qp(Q, p, G, h)
        monkeypatch.undo()
        monkeypatch.setattr(_dual_native, "certify", leaves_row_9)
        sol = solve_qp(Q, p, G, h)
    assert bool((sol.status == Status.SOLVED).all()) and torch.equal(sol.status, ref.status)
    torch.testing.assert_close(sol.x[9], ref.x[9], atol=1e-12, rtol=1e-12)


def _filter_qp() -> tuple[torch.Tensor, ...]:
    """An elastic filter QP (two controls of weights 1 and 1e-3, a slack of weight 1.8e5)
    whose optimum has the second control on its lower bound with a multiplier of 5e7."""
    Q = torch.diag(torch.tensor([1.0, 1e-3, 1.8e5], dtype=F64))
    p = torch.tensor([15.2, 0.0693, 1.8e5], dtype=F64)
    G = torch.tensor(
        [
            [-0.5714, 0.8207, -1.0],
            [-0.5636, 0.8260, -1.0],
            [-0.4414, -0.8973, -1.0],
            [-0.4255, 0.9050, -1.0],
            [0.1436, 0.9896, -1.0],
        ],
        dtype=F64,
    )
    h = torch.tensor([1025.9, 1743.1, 1360.3, -385.35, 732.16], dtype=F64)
    lb = torch.tensor([-40.0, -40.0, 0.0], dtype=F64)
    ub = torch.tensor([40.0, 40.0, math.inf], dtype=F64)
    return Q, p, G, h, lb, ub


def test_active_rows_hold_to_rounding_under_a_large_multiplier(cvx):
    """The dual method's point lies on its active rows to rounding although a multiplier of
    5e7 over a curvature of 1e-3 leaves its Schur complement 1e-5 off: one state alone, a
    few, and a batch give the same controls."""
    Q, p, G, h, lb, ub = _filter_qp()
    ref, _, status = cvx(*(t.numpy() for t in (Q, p, G, h)), lb=lb.numpy(), ub=ub.numpy())
    assert status == "optimal"
    answers = []
    for B in (1, 3, 200):
        with torch.no_grad():
            Qb, pb, Gb, hb, lbb, ubb = (t.expand(B, *t.shape) for t in (Q, p, G, h, lb, ub))
            sol = solve_qp(Qb, pb, Gb, hb, lb=lbb, ub=ubb)
        assert bool((sol.status == Status.SOLVED).all())
        assert float(sol.lam_lb[0, 1]) > 1e7
        answers.append(sol.x[0])
    for x in answers:
        assert abs(float(x[1]) + 40.0) <= 1e-12 * 40.0
        assert np.abs(x.numpy() - ref).max() <= 1e-6 * (1 + np.abs(ref).max())
        torch.testing.assert_close(x, answers[0], atol=1e-9, rtol=0)
