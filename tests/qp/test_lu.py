"""The batched LU factorisation of the QP layer against one matrix at a time, with several
torch threads and orders where torch's batched CPU factorisation is known to break."""

from __future__ import annotations

import pytest
import torch

from torchcbf.qp._lu import ONE_AT_A_TIME_FROM, lu_factor_ex


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(3, 163), (2, 2, 200), (4, ONE_AT_A_TIME_FROM - 1), (1, 170)])
def test_factors_reproduce_every_matrix(two_threads, shape, dtype):
    *batch, N = shape
    g = torch.Generator().manual_seed(N)
    K = torch.randn(*batch, N, N, generator=g, dtype=torch.float64).to(dtype)
    LU, pivots, info = lu_factor_ex(K)
    assert LU.shape == K.shape and pivots.shape == (*batch, N) and info.shape == tuple(batch)
    assert bool((info == 0).all()) and bool(((pivots >= 1) & (pivots <= N)).all())
    P, L, U = torch.lu_unpack(LU, pivots)
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    torch.testing.assert_close(P @ L @ U, K, atol=tol, rtol=tol)
    for idx in torch.cartesian_prod(*(torch.arange(b) for b in batch)).reshape(-1, len(batch)):
        one = torch.linalg.lu_factor_ex(K[tuple(idx)])
        assert torch.equal(pivots[tuple(idx)], one.pivots)
        torch.testing.assert_close(LU[tuple(idx)], one.LU, atol=tol, rtol=tol)
