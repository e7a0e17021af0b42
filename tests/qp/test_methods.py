"""The solver table: which method ``solve_qp`` picks, and ``QPSolution.method`` naming the
algorithm that answered each row (rows one method cannot certify are answered by another)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcbf.qp import Status, solve_qp
from torchcbf.qp._function import ANSWERED_BY, SOLVERS
from torchcbf.qp.solve import METHODS_ANSWERED

F64 = torch.float64


def _batch(B: int, n: int, m: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    L = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = L @ L.mT + 0.1 * torch.eye(n, dtype=F64)
    p = torch.randn(B, n, generator=g, dtype=F64)
    box = torch.cat((torch.eye(n, dtype=F64), -torch.eye(n, dtype=F64)))
    G = torch.cat((box, torch.randn(m, n, generator=g, dtype=F64))).expand(B, -1, -1)
    h = torch.ones(B, 2 * n + m, dtype=F64)
    return Q.contiguous(), p, G.contiguous(), h


def test_the_table_names_every_method_and_the_codes_their_names():
    assert set(SOLVERS) == {
        "closed_form", "active_set", "eliminate", "enumerate", "ipm", "auto_proxsuite", "outside",
    }  # fmt: skip
    assert METHODS_ANSWERED == ANSWERED_BY
    assert len(set(ANSWERED_BY)) == len(ANSWERED_BY)


@pytest.mark.parametrize(
    ("method", "path", "name"),
    [
        ("active_set", "active_set_native", "active_set"),
        ("enumerate", "enumerate", "enumerate"),
        ("ipm", "ipm", "ipm"),
    ],
)
def test_the_method_asked_for_answers_every_row(method, path, name):
    Q, p, G, h = _batch(12, 3, 2, seed=1)
    Q.requires_grad_()  # the general path (no real-time shortcut)
    sol = solve_qp(Q, p, G, h, method=method)
    assert bool((sol.status == Status.SOLVED).all())
    assert sol.path == path
    assert sol.method.shape == (12,) and sol.method.dtype == torch.int64
    assert sol.method_names() == [name] * 12


def test_each_row_reports_the_method_that_answered_it(cvx):
    """A rank-one ``Q`` is certified on the dual method's active set, ``Q = 0`` with few
    candidate active sets by enumeration, ``Q = 0`` with many by the interior point method;
    their answers agree with Clarabel."""
    Q, p, G, h = _batch(8, 3, 2, seed=2)
    Q[3] = torch.diag(torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    Q[5] = 0.0
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    assert bool((sol.status == Status.SOLVED).all())
    names = sol.method_names()
    assert names[5] == "enumerate"
    assert all(names[i] == "active_set" for i in range(8) if i != 5)
    for i in (3, 5):
        ref, _, status = cvx(Q[i].numpy(), p[i].numpy(), G[i].numpy(), h[i].numpy())
        assert status == "optimal"
        assert np.abs(sol.x[i].numpy() - ref).max() <= 1e-6

    n, m = 6, 40  # an LP with too many candidate active sets to enumerate
    Q, p, G, h = _batch(8, n, m, seed=3)
    Q[1] = 0.0
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    assert bool((sol.status == Status.SOLVED).all())
    assert sol.method_names() == ["active_set", "ipm"] + ["active_set"] * 6
    ref, _, status = cvx(Q[1].numpy(), p[1].numpy(), G[1].numpy(), h[1].numpy())
    assert status == "optimal"
    assert np.abs(sol.x[1].numpy() - ref).max() <= 1e-6


def test_shortcuts_and_empty_batches_report_methods():
    Q, p, G, h = _batch(2, 3, 2, seed=4)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    assert sol.path == "small_native" and sol.method_names() == ["active_set"] * 2
    empty = solve_qp(Q[:0], p[:0], G[:0], h[:0])
    assert empty.path == "empty" and empty.method.shape == (0,)


@pytest.mark.parametrize("kw", [{}, {"method": "ipm"}, {"method": "enumerate"}])
@pytest.mark.parametrize("B", [1, 3])
def test_rows_no_method_answered_say_none(kw, B):
    """A row with a NaN is NON_FINITE before any method runs: its method is ``"none"``,
    not the algorithm that solved the other rows."""
    Q, p, G, h = _batch(B, 2, 1, seed=3)
    p[0, 0] = float("nan")
    sol = solve_qp(Q, p, G, h, **kw)
    assert int(sol.status[0]) == Status.NON_FINITE
    names = sol.method_names()
    assert names[0] == "none"
    assert "none" not in names[1:] and (sol.status[1:] == Status.SOLVED).all()
