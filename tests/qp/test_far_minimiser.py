"""Problems whose unconstrained minimiser lies far outside the feasible set (a linear term
many orders above the constraints): a row the exact methods certify satisfies its
constraints on the scale of the answer, and ``solve_qp`` matches Clarabel on every row it
calls solved."""

from __future__ import annotations

import pytest
import torch

from torchcbf.qp import Status, _dual_native, solve_qp
from torchcbf.qp._dual import solve_dual

F64 = torch.float64
SCALES = [1e2, 1e8, 1e12, 1e20, 1e100]
NO_KERNEL = "the C kernel of the dual method was not built"
ENGINES = ["torch", pytest.param("c", marks=pytest.mark.skipif(not _dual_native.available(),
                                                               reason=NO_KERNEL))]  # fmt: skip


def _problems(scale: float, B: int = 32, n: int = 3, seed: int = 0):
    """``P = I``, the box ``|x| <= 1`` and ``sum(x) <= 0.5``, ``q = -scale d``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(B, n, generator=g, dtype=F64)
    eye = torch.eye(n, dtype=F64)
    G = torch.cat((eye, -eye, torch.ones(1, n, dtype=F64)), 0).expand(B, -1, -1)
    h = torch.cat((torch.ones(2 * n, dtype=F64), torch.tensor([0.5], dtype=F64))).expand(B, -1)
    return eye.expand(B, n, n), -scale * d, G, h


def _violation(G, h, x):
    return ((G @ x.unsqueeze(-1)).squeeze(-1) - h).amax(-1)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("scale", SCALES)
def test_certified_rows_satisfy_their_constraints(engine, scale):
    P, q, G, h = _problems(scale)
    out = solve_dual(P, q, G, h, eps=1e-7, max_iter=100, engine=engine)
    assert out.ok.any()
    assert float(_violation(G, h, out.x)[out.ok].max()) <= 1e-9


@pytest.mark.parametrize("scale", SCALES)
def test_solved_rows_match_clarabel(cvx, scale):
    P, q, G, h = _problems(scale, B=8, seed=1)
    sol = solve_qp(P, q, G, h)
    solved = sol.status == Status.SOLVED
    assert solved.any()
    assert float(_violation(G, h, sol.x)[solved].max()) <= 1e-9
    for i in solved.nonzero().flatten().tolist():
        # the same minimiser: the objective divided by the scale
        ref, _, status = cvx((P[i] / scale).numpy(), (q[i] / scale).numpy(), G[i].numpy(),
                             h[i].numpy())  # fmt: skip
        assert status == "optimal"
        torch.testing.assert_close(sol.x[i], torch.from_numpy(ref), atol=1e-6, rtol=1e-6)
