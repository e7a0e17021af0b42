"""Problems with thousands of rows and few of them active: the interior point method's
polish solves on the active rows only (``_kkt.solve_active``), checked against Clarabel and
against the full active-set KKT system."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcbf.qp import Status, _kkt, solve_qp
from torchcbf.qp._data import QPData

F64 = torch.float64


def _many_rows(B: int, n: int, m: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT / n + 0.5 * torch.eye(n, dtype=F64)
    p = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    G = torch.randn(B, m, n, generator=g, dtype=F64)
    h = 0.2 + torch.rand(B, m, generator=g, dtype=F64)
    return Q, p, G, h


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_interior_point_with_thousands_of_rows_matches_clarabel(cvx, dtype):
    data = _many_rows(2, 8, 3000, seed=1)
    sol = solve_qp(*(t.to(dtype) for t in data), method="ipm")
    assert bool((sol.status == Status.SOLVED).all())
    tol = 1e-7 if dtype == F64 else 1e-3
    for i in range(2):
        ref, _, status = cvx(*(t[i].numpy() for t in data))
        assert status == "optimal"
        assert np.abs(sol.x[i].double().numpy() - ref).max() <= tol * (1 + np.abs(ref).max())
        assert int((sol.lam[i] > 0).sum()) <= 8


def test_solve_active_solves_the_active_rows_kkt_system():
    g = torch.Generator().manual_seed(4)
    B, n, M, E = 6, 5, 12, 2
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    P = L @ L.mT + torch.eye(n, dtype=F64)
    q, h = torch.randn(B, n, generator=g, dtype=F64), torch.randn(B, M, generator=g, dtype=F64)
    G, A = (
        torch.randn(B, M, n, generator=g, dtype=F64),
        torch.randn(B, E, n, generator=g, dtype=F64),
    )
    b = torch.randn(B, E, generator=g, dtype=F64)
    # 0 to n - E active rows per problem, at scattered positions
    act = torch.zeros(B, M, dtype=torch.bool)
    for i, rows in enumerate(([], [0, 1, 2], [7], [3, 11], [2, 5, 9], [10])):
        act[i, rows] = True
    x, z, y, ok = _kkt.solve_active(QPData(P, q, G, h, A, b), act, steps=8)
    assert bool(ok.all())
    # the exact KKT system on the active rows, solved by a dense solve row by row
    for i in range(B):
        Ga = G[i][act[i]]
        k = Ga.shape[0]
        K = torch.zeros(n + k + E, n + k + E, dtype=F64)
        K[:n, :n], K[:n, n : n + k], K[n : n + k, :n] = P[i], Ga.T, Ga
        K[:n, n + k :], K[n + k :, :n] = A[i].T, A[i]
        w = torch.linalg.solve(K, torch.cat((-q[i], h[i][act[i]], b[i])))
        torch.testing.assert_close(x[i], w[:n], atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(z[i][act[i]], w[n : n + k], atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(y[i], w[n + k :], atol=1e-10, rtol=1e-10)
    assert float(z[~act].abs().max()) == 0.0
