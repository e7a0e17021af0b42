"""Fixtures for the QP tests: a cvxpy (Clarabel) reference solver."""

from __future__ import annotations

import numpy as np
import pytest


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


def pytest_collection_modifyitems(config, items):
    """Skip this package's ``slow`` tests unless selected with ``-m slow`` (or env
    ``TORCHCBF_SLOW=1``), so the default run stays fast."""
    import os

    markexpr = config.getoption("-m") or ""
    if os.environ.get("TORCHCBF_SLOW") == "1" or (
        "slow" in markexpr and "not slow" not in markexpr
    ):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow or TORCHCBF_SLOW=1")
    here = os.path.dirname(__file__)
    for item in items:
        if "slow" in item.keywords and str(item.fspath).startswith(here):
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def _single_thread():
    """Tiny batched kernels are slower with an OpenMP team on a shared 2-core machine."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
