"""The Maros-Meszaros-format reader, the Clarabel reference and the judge."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcbf.qp import Status, solve_qp
from torchcbf.qp.maros_meszaros import (
    clarabel_reference,
    dense_subset,
    judge,
    load_problem,
    proxsuite_dense,
)

scipy_io = pytest.importorskip("scipy.io")
sp = pytest.importorskip("scipy.sparse")


def _write(path, n_extra_rows: int = 0):
    """``min 1/2 |x|^2 - x1 - x2`` s.t. ``x1 + x2 <= 1`` (one-sided), ``x1 - x2 = 0.25``
    (equal sides), ``-5 <= x1 + 2 x2`` (a lower side only), ``0 <= x <= 1e20`` (no upper
    bound), in the file format: A ends with the identity, 1e20 is no bound."""
    C = np.array([[1.0, 1.0], [1.0, -1.0], [1.0, 2.0]])
    A = np.vstack((C, np.eye(2)))
    lo = np.array([-1e20, 0.25, -5.0, 0.0, 0.0])
    hi = np.array([1.0, 0.25, 1e20, 1e20, 1e20])
    scipy_io.savemat(
        path,
        {
            "P": sp.csc_matrix(np.eye(2)),
            "q": np.array([[-1.0, -1.0]]),
            "A": sp.csc_matrix(A),
            "l": lo[None],
            "u": hi[None],
            "n": np.array([[2]]),
            "m": np.array([[5]]),
        },
    )


def test_reader_splits_rows_as_the_format_says(tmp_path):
    _write(tmp_path / "TOY.mat")
    prob = load_problem(tmp_path / "TOY.mat")
    assert prob.name == "TOY" and prob.n == 2
    np.testing.assert_array_equal(prob.A, [[1.0, -1.0]])
    np.testing.assert_array_equal(prob.b, [0.25])
    np.testing.assert_array_equal(prob.G, [[1.0, 1.0], [-1.0, -2.0]])
    np.testing.assert_array_equal(prob.h, [1.0, 5.0])
    np.testing.assert_array_equal(prob.lb, [0.0, 0.0])
    assert np.isinf(prob.ub).all()
    assert prob.constraints == 2 + 1 + 2
    assert load_problem(tmp_path / "TOY.mat", max_constraints=4) is None
    assert [p.name for p in dense_subset(tmp_path)] == ["TOY"]


def test_judge_against_clarabel(tmp_path):
    pytest.importorskip("clarabel")
    _write(tmp_path / "TOY.mat")
    prob = load_problem(tmp_path / "TOY.mat")
    ref = clarabel_reference(prob)
    assert ref.status == "optimal"
    np.testing.assert_allclose(ref.x, [0.625, 0.375], atol=1e-8)
    t = [torch.from_numpy(v) for v in (prob.P, prob.q, prob.G, prob.h, prob.A, prob.b,
                                       prob.lb, prob.ub)]  # fmt: skip
    sol = solve_qp(*t)
    assert int(sol.status) == Status.SOLVED
    assert judge(prob, sol.x.numpy(), True, False, ref, tol=1e-6) == "right"
    assert judge(prob, np.array([0.7, 0.45]), True, False, ref, tol=1e-6) == "wrong"  # infeasible
    assert judge(prob, np.array([0.6, 0.35]), True, False, ref, tol=1e-6) == "wrong"  # worse
    assert judge(prob, sol.x.numpy(), False, True, ref, tol=1e-6) == "false_certificate"
    assert judge(prob, sol.x.numpy(), False, False, ref, tol=1e-6) == "failed"
    peer = proxsuite_dense(prob)
    assert judge(prob, peer.x, True, False, ref, tol=1e-6) == "right"
