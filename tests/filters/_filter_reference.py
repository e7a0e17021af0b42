"""Independent references for the filter tests: hand-written CBF/CLF rows and cvxpy QPs.

The scene: a unicycle (x, y, theta; v, omega), two ball obstacles (one batched Ball module
with k = 2) and one half-space wall, plus a quadratic Lyapunov function of the position.
Every Lie derivative below is written out by hand in numpy (no autograd).
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
from scipy.special import erfinv

CENTERS = np.array([[1.0, 0.5], [-1.0, 1.5]])
RADII = np.array([0.6, 0.4])
WALL_A = np.array([0.0, 1.0])  # h = b - a'p
WALL_B = 2.5
GOAL = np.array([2.0, 2.0])
GAINS = np.array([1.0, 2.0, 0.5])  # alpha per barrier output
CLF_RATE = 0.7
U_MIN = np.array([-1.0, -2.0])
U_MAX = np.array([1.5, 2.0])
R = np.diag([1.0, 0.5])
CLF_W = 100.0
SIGMA = 0.2
W_MAX = np.array([0.1, 0.2, 0.05])
BETA = 0.3
RHO, HORIZON, ETA = 0.1, 2.0, np.array([0.5, 0.4, 0.3])
CLF_ETA, CLF_GAMMA = 0.6, 0.25


def g_unicycle(x: np.ndarray) -> np.ndarray:
    th = x[2]
    return np.array([[np.cos(th), 0.0], [np.sin(th), 0.0], [0.0, 1.0]])


def rows(x: np.ndarray, mode: str) -> tuple[np.ndarray, ...]:
    """``(a [k, m], b [k], aV [1, m], bV [1], h [k])`` of the scene at one state."""
    p = x[:2]
    g = g_unicycle(x)
    h = np.concatenate([((p - CENTERS) ** 2).sum(-1) - RADII**2, [WALL_B - WALL_A @ p]])
    dhdx = np.zeros((3, 3))
    dhdx[:2, :2] = 2 * (p - CENTERS)
    dhdx[2, :2] = -WALL_A
    a = dhdx @ g
    lfh = np.zeros(3)  # unicycle drift is zero
    V = ((p - GOAL) ** 2).sum()
    dVdx = np.array([*(2 * (p - GOAL)), 0.0])
    aV = (dVdx @ g)[None]
    tr_h = np.array([4 * SIGMA**2, 4 * SIGMA**2, 0.0])  # tr(s' H s) = sigma^2 tr(H)
    tr_V = 4 * SIGMA**2
    if mode == "vanilla":
        b = lfh + GAINS * h
        bV = np.array([CLF_RATE * V])
    elif mode == "robust":
        b = lfh + GAINS * h - np.abs(dhdx) @ W_MAX
        bV = np.array([CLF_RATE * V + np.abs(dVdx) @ W_MAX])
    elif mode == "stochastic":
        b = lfh + 0.5 * tr_h + GAINS * h - BETA
        bV = np.array([0.5 * tr_V + CLF_RATE * V])
    else:
        delta = np.sqrt(2 * HORIZON) * ETA * erfinv(1 - RHO)
        delta_v = np.sqrt(2 * HORIZON) * CLF_ETA * erfinv(1 - RHO)
        b = lfh + 0.5 * tr_h + (h - delta) / HORIZON
        bV = np.array([0.5 * tr_V + (V - CLF_GAMMA + delta_v) / HORIZON])
    return a, b, aV, bV, h


class _Problems:
    """The two cvxpy problems, parametrised (DPP) so that they compile once."""

    def __init__(self) -> None:
        self.a, self.b = cp.Parameter((3, 2)), cp.Parameter(3)
        self.aV, self.bV = cp.Parameter((1, 2)), cp.Parameter(1)
        self.u_nom = cp.Parameter(2)
        self.u, d = cp.Variable(2), cp.Variable(1)
        rbar = np.trace(R) / 2
        r_half = np.linalg.cholesky(R).T  # R = r_half' r_half; sum_squares keeps the problem DPP
        obj = 0.5 * cp.sum_squares(r_half @ (self.u - self.u_nom))
        obj = obj + 0.5 * CLF_W * rbar * cp.sum_squares(d)
        cons = [
            self.a @ self.u + self.b >= 0,
            self.aV @ self.u + self.bV <= d,
            d >= 0,
            self.u >= U_MIN,
            self.u <= U_MAX,
        ]
        self.qp = cp.Problem(cp.Minimize(obj), cons)
        # least violation: a and b pre-divided by the row norms
        self.an, self.bn = cp.Parameter((3, 2)), cp.Parameter(3)
        v = cp.Variable(2)
        self.lp = cp.Problem(
            cp.Minimize(cp.max(cp.pos(-(self.an @ v + self.bn)))), [v >= U_MIN, v <= U_MAX]
        )


_PROBLEMS: list[_Problems] = []


def _problems() -> _Problems:
    if not _PROBLEMS:
        _PROBLEMS.append(_Problems())
    return _PROBLEMS[0]


def solve_reference(
    x: np.ndarray, u_nom: np.ndarray, mode: str, clf: bool = True
) -> np.ndarray | None:
    """The hard-constrained CBF / relaxed CLF QP in cvxpy (Clarabel); ``None`` if infeasible.

    ``clf=False`` drops the CLF (its row becomes ``0 <= delta``)."""
    P = _problems()
    P.a.value, P.b.value, aV, bV, _ = rows(x, mode)
    P.aV.value, P.bV.value = (aV, bV) if clf else (0 * aV, 0 * bV)
    P.u_nom.value = u_nom
    P.qp.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    if P.qp.status == cp.INFEASIBLE:
        return None
    assert P.qp.status == cp.OPTIMAL, P.qp.status
    return P.u.value


def least_violation(x: np.ndarray, mode: str) -> float:
    """``min_u max_i max(0, -(a_i u + b_i) / |a_i|)`` over the control box (an LP)."""
    a, b, *_ = rows(x, mode)
    n = np.maximum(np.linalg.norm(a, axis=1), 1e-6)
    P = _problems()
    P.an.value, P.bn.value = a / n[:, None], b / n
    P.lp.solve(solver=cp.CLARABEL)
    return float(P.lp.value)
