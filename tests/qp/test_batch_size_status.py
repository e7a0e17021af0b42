"""A row's status does not depend on the batch around it: a numerical failure in a batched
factorisation is a per-row status (never an exception), and the same problem gets the same
status alone and in batches of any size."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.qp import Status, solve_qp


def _fuzz_problem(B: int, N: int, M: int, seed: int):
    """The QP family of scripts/fuzz_kernels.py: a shared ``Q``, ``x = 0`` feasible."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    R = torch.randn(1, N, N, generator=g, dtype=f64)
    Q = (R @ R.mT / N + 0.5 * torch.eye(N, dtype=f64)).expand(B, N, N)
    p = torch.randn(B, N, generator=g, dtype=f64)
    G = torch.randn(B, M, N, generator=g, dtype=f64)
    h = torch.rand(B, M, generator=g, dtype=f64) + 0.1
    return Q, p, G, h


@pytest.mark.parametrize("broken", ["pivots", "factor", "nan"])
@pytest.mark.parametrize("method", ["ipm", "active_set", "auto"])
def test_broken_batched_lu_is_a_status_not_an_exception(cvx, monkeypatch, broken, method):
    """A batched LU that comes back broken without saying so (as MKL's can after
    ``torch.set_num_threads``: pivots out of range, or a factor that does not reproduce the
    matrix) leaves every row with an honest status; a ``SOLVED`` row is right."""
    B, N, M = 5, 64, 6
    Q, p, G, h = _fuzz_problem(B, N, M, seed=1595054439)
    lb = torch.full((B, N), -math.inf, dtype=torch.float64)
    ub = torch.full((B, N), 2.0, dtype=torch.float64)
    real = torch.linalg.lu_factor_ex

    def lu_factor_ex(K, *args, **kwargs):
        LU, pivots, info = real(K, *args, **kwargs)
        if K.dim() == 3 and K.shape[0] > 1:  # every second row of a batch is broken
            if broken == "pivots":
                pivots = pivots.clone()
                pivots[::2] = 0
            elif broken == "factor":
                LU = LU.clone()
                LU[::2] = LU[::2] + 3.0
            else:
                LU = LU.clone()
                LU[::2, 0, 0] = math.nan
        return LU, pivots, info

    monkeypatch.setattr(torch.linalg, "lu_factor_ex", lu_factor_ex)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    monkeypatch.undo()
    assert sol.status.shape == (B,)
    assert torch.isfinite(sol.x).all()
    for i in range(B):
        if int(sol.status[i]) != int(Status.SOLVED):
            assert int(sol.status[i]) in (Status.NUMERICAL_ERROR, Status.MAX_ITER)
            continue
        x_ref, _, status = cvx(Q[i].numpy(), p[i].numpy(), G[i].numpy(), h[i].numpy(),
                               lb=lb[i].numpy(), ub=ub[i].numpy())  # fmt: skip
        assert status == "optimal"
        ref = torch.from_numpy(x_ref)
        assert float((sol.x[i] - ref).abs().max()) <= 1e-6 * (1 + float(ref.abs().max()))


def _elastic(B: int, seed: int = 0):
    """Filter-like QPs: two controls with a rotated weight of condition 1e3 and a slack
    ``s >= 0`` (no upper bound) of weight 5e5 softening three rows (always feasible);
    ``cond(Q) ~ 5e8``."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    V = torch.linalg.qr(torch.randn(B, 2, 2, generator=g, dtype=f64)).Q
    Qu = V @ torch.diag(torch.tensor([1e-3, 1.0], dtype=f64)) @ V.mT
    Q = torch.zeros(B, 3, 3, dtype=f64)
    Q[:, :2, :2] = Qu
    Q[:, 2, 2] = 5e5
    u_nom = 2 * torch.randn(B, 2, generator=g, dtype=f64)
    p = torch.cat((-(Qu @ u_nom.unsqueeze(-1)).squeeze(-1), torch.full((B, 1), 5e5)), -1)
    Lg = torch.randn(B, 3, 2, generator=g, dtype=f64)
    G = torch.cat((-Lg, -torch.ones(B, 3, 1, dtype=f64)), -1)
    h = 3 * torch.randn(B, 3, generator=g, dtype=f64)
    lb = torch.tensor([-1.0, -1.0, 0.0], dtype=f64).expand(B, 3)
    ub = torch.tensor([1.0, 1.0, math.inf], dtype=f64).expand(B, 3)
    return Q, p, G, h, lb, ub


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("method", ["auto", "ipm"])
def test_elastic_filter_qp_status_does_not_depend_on_batch_size(method, dtype):
    data = [t.to(dtype) for t in _elastic(130)]
    full = solve_qp(*data[:4], lb=data[4], ub=data[5], method=method)
    assert (full.status == int(Status.SOLVED)).all()
    for B in (1, 16, 64, 65):
        part = solve_qp(*(t[:B] for t in data[:4]), lb=data[4][:B], ub=data[5][:B], method=method)
        assert torch.equal(part.status, full.status[:B]), B
        tol = 1e-7 if dtype == torch.float64 else 2e-3
        torch.testing.assert_close(part.x, full.x[:B], atol=tol, rtol=tol)
    # copies of one problem: 64 and 65 of them (the few-failed-rows threshold)
    for B in (64, 65):
        copies = [t[:1].expand(B, *t.shape[1:]) for t in data]
        out = solve_qp(*copies[:4], lb=copies[4], ub=copies[5], method=method)
        assert (out.status == int(full.status[0])).all(), B


def _box_corner_problem(pull: float):
    """``(Q, p, G, h, lb, ub, x*)``: two controls in a box of 2 pulled by ``p = -pull`` to
    its corner, two rows with their own slack variables (weight 100); ``x*`` the corner
    and the rows' slacks there."""
    f64 = torch.float64
    Q = torch.diag(torch.tensor([1.0, 1.0, 100.0, 100.0], dtype=f64))
    G = torch.tensor([[0.83, 0.56, -1.0, 0.0], [0.32, 0.95, 0.0, -1.0]], dtype=f64)
    h = torch.tensor([1.11, 1.45], dtype=f64)
    lb = torch.tensor([-2.0, -2.0, 0.0, 0.0], dtype=f64)
    ub = torch.tensor([2.0, 2.0, math.inf, math.inf], dtype=f64)
    p = torch.tensor([-pull, -pull, 0.0, 0.0], dtype=f64)
    u = torch.tensor([2.0, 2.0], dtype=f64)
    return Q, p, G, h, lb, ub, torch.cat((u, G[:, :2] @ u - h))


@pytest.mark.parametrize("hard", [1, 16, 17, 40])
def test_a_rows_answer_does_not_depend_on_how_many_rows_are_hard(hard):
    """A far unconstrained minimiser (``p`` of 1e12) that enumeration by Schur complement
    loses: the rescue solved every candidate's KKT system only while few rows (16) needed
    it; the 17th sent them all to the interior point method, which ended NUMERICAL_ERROR."""
    Q, p_hard, G, h, lb, ub, expected = _box_corner_problem(1e12)
    B = 64
    p = torch.tensor([-0.1, 0.2, 0.0, 0.0], dtype=torch.float64).repeat(B, 1)
    p[:hard] = p_hard

    def expand(t):
        return t.expand(B, *t.shape)

    sol = solve_qp(expand(Q), p, expand(G), expand(h), lb=expand(lb), ub=expand(ub))
    assert (sol.status == Status.SOLVED).all(), sol.status
    torch.testing.assert_close(sol.x[:hard], expected.expand(hard, 4), rtol=0, atol=1e-9)


@pytest.mark.parametrize("scale", [1e12, 1e13, 1e14, 1e16, 1e20])
@pytest.mark.parametrize("method", ["auto", "active_set", "enumerate"])
def test_a_far_minimiser_beside_a_box_is_solved_at_any_distance(method, scale):
    """``p`` of 1e13, 1e14 or 1e20 (not 1e12 or 1e16) ended NUMERICAL_ERROR: enumeration by
    Schur complement took a candidate a rounding off, which no polish certified, and the
    rescue on each candidate's own KKT system ran only where it had found none."""
    Q, p, G, h, lb, ub, expected = _box_corner_problem(scale)
    sol = solve_qp(Q, p, G, h, lb=lb, ub=ub, method=method)
    assert int(sol.status) == Status.SOLVED
    torch.testing.assert_close(sol.x, expected, rtol=0, atol=1e-9)
