"""Independent references for the filter tests: hand-written CBF/CLF rows and cvxpy QPs.

The scene: a unicycle (x, y, theta; v, omega), two ball obstacles (one batched Ball module
with k = 2) and one half-space wall, plus a quadratic Lyapunov function of the position.
A second scene (``rectified_rows``): two rotated, scaled ellipses rectified into exponential
CBFs on an acceleration-controlled unicycle. Every Lie derivative below is written out by
hand in numpy (no autograd).
"""

from __future__ import annotations

import numpy as np
import pytest
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


def _cvxpy():
    """cvxpy, imported where a reference needs it (a test without it is skipped)."""
    return pytest.importorskip("cvxpy")


class _Problems:
    """The two cvxpy problems, parametrised (DPP) so that they compile once."""

    def __init__(self) -> None:
        cp = _cvxpy()
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
    cp = _cvxpy()
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
    cp = _cvxpy()
    P = _problems()
    P.an.value, P.bn.value = a / n[:, None], b / n
    P.lp.solve(solver=cp.CLARABEL)
    return float(P.lp.value)


# A second scene: an acceleration-controlled unicycle (x, y, v, theta; a, omega) and two
# rotated, scaled ellipses rectified into exponential CBFs of relative degree two,
# h_e = L_f h + K0 h, with h = s ((q / a)^2 summed - 1), q = R(angle)' (p - c).
ELLIPSE_CENTERS = np.array([[2.0, 1.0], [-0.5, 2.5]])
ELLIPSE_AXES = np.array([[0.8, 0.4], [0.5, 1.0]])
ELLIPSE_ANGLES = np.array([0.3, -0.6])
ELLIPSE_SCALES = np.array([1.5, 0.5])
K0 = 2.0
ELLIPSE_GAINS = np.array([1.0, 3.0])
ACCEL_U_MIN = np.array([-2.0, -1.5])
ACCEL_U_MAX = np.array([2.0, 1.5])
ACCEL_SIGMA = 0.25
ACCEL_W_MAX = np.array([0.05, 0.05, 0.1, 0.1])
ACCEL_ETA = np.array([0.4, 0.3])


def rectified_rows(x: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a [2, m], b [2], h_e [2])`` of the rectified-ellipse scene at one state."""
    p, v, th = x[:2], x[2], x[3]
    heading = np.array([np.cos(th), np.sin(th)])
    turn = np.array([-np.sin(th), np.cos(th)])
    a, b, hs = [], [], []
    for c, axes, ang, s, gain, eta in zip(
        ELLIPSE_CENTERS,
        ELLIPSE_AXES,
        ELLIPSE_ANGLES,
        ELLIPSE_SCALES,
        ELLIPSE_GAINS,
        ACCEL_ETA,
        strict=True,
    ):
        rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        D = np.diag(1.0 / axes**2)
        q = rot.T @ (p - c)
        h = s * (q @ D @ q - 1.0)
        grad_p = 2 * s * rot @ D @ q
        H_p = 2 * s * rot @ D @ rot.T
        fp = v * heading
        h_e = grad_p @ fp + K0 * h
        dhdx = np.concatenate([H_p @ fp + K0 * grad_p, [grad_p @ heading, v * grad_p @ turn]])
        lfh = dhdx[:2] @ fp
        lgh = dhdx[2:]  # g = [0; I] on (v, theta)
        tr = ACCEL_SIGMA**2 * (K0 * np.trace(H_p) - v * grad_p @ heading)
        if mode == "vanilla":
            row_b = lfh + gain * h_e
        elif mode == "robust":
            row_b = lfh + gain * h_e - np.abs(dhdx) @ ACCEL_W_MAX
        elif mode == "stochastic":
            row_b = lfh + 0.5 * tr + gain * h_e - BETA
        else:
            delta = np.sqrt(2 * HORIZON) * eta * erfinv(1 - RHO)
            row_b = lfh + 0.5 * tr + (h_e - delta) / HORIZON
        a.append(lgh)
        b.append(row_b)
        hs.append(h_e)
    return np.stack(a), np.array(b), np.array(hs)


def solve_rectified_reference(x: np.ndarray, u_nom: np.ndarray, mode: str) -> np.ndarray | None:
    """The hard-constrained CBF QP of the rectified-ellipse scene in cvxpy (Clarabel, weight
    ``R``, box ``ACCEL_U_MIN..ACCEL_U_MAX``); ``None`` if infeasible."""
    cp = _cvxpy()
    a, b, _ = rectified_rows(x, mode)
    u = cp.Variable(2)
    r_half = np.linalg.cholesky(R).T
    problem = cp.Problem(
        cp.Minimize(0.5 * cp.sum_squares(r_half @ (u - u_nom))),
        [a @ u + b >= 0, u >= ACCEL_U_MIN, u <= ACCEL_U_MAX],
    )
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    if problem.status == cp.INFEASIBLE:
        return None
    assert problem.status == cp.OPTIMAL, problem.status
    return u.value
