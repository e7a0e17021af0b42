"""Fixtures for the QP tests: a cvxpy (Clarabel) reference solver, and a switch that runs a
test without and with the C kernel of the dual active-set method."""

from __future__ import annotations

import numpy as np
import pytest

from torchcbf.qp import _dual_native


def cvxpy_solve(Q, p, G=None, h=None, A=None, b=None, lb=None, ub=None):
    """Solve one QP with cvxpy/Clarabel; returns ``(x, objective, status_string)``."""
    import cvxpy as cp

    n = Q.shape[0]
    x = cp.Variable(n)
    cons = []
    if G is not None and G.shape[0] > 0:
        cons.append(G @ x <= h)
    if A is not None and A.shape[0] > 0:
        cons.append(A @ x == b)
    if lb is not None:
        fin = np.isfinite(lb)
        if fin.any():
            cons.append(x[np.flatnonzero(fin)] >= lb[fin])
    if ub is not None:
        fin = np.isfinite(ub)
        if fin.any():
            cons.append(x[np.flatnonzero(fin)] <= ub[fin])
    Qs = 0.5 * (Q + Q.T)
    prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, cp.psd_wrap(Qs)) + p @ x), cons)
    prob.solve(
        solver="CLARABEL", tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, tol_ktratio=1e-9
    )
    return x.value, prob.value, prob.status


@pytest.fixture
def cvx():
    pytest.importorskip("cvxpy")
    return cvxpy_solve


@pytest.fixture(params=[False, True], ids=["torch", "kernel"])
def kernel(request, monkeypatch) -> bool:
    """``False``: the C kernel is switched off (the torch implementation, and the closed
    form, run on the CPU); ``True``: it runs (skipped where it was not built)."""
    if not request.param:
        # simulates a kernel that failed to build: no public switch runs the torch
        # implementation on the CPU while the kernel is there
        monkeypatch.setattr(_dual_native, "available", lambda: False)
    elif not _dual_native.available():
        pytest.skip("the C kernel of the dual method was not built")
    return request.param
