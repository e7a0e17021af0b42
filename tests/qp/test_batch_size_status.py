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
