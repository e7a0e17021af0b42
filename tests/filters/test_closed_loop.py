"""Closed-loop properties: invariance of the safe set, robustness to a worst-case
disturbance, CLF convergence, CBF+CLF reach-avoid (torchcbf.sim.simulate, RK4)."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch

from torchcbf.barriers import Ball, QuadraticLyapunov, rectify
from torchcbf.dynamics import ControlAffine, DoubleIntegrator, SingleIntegrator, Unicycle
from torchcbf.filters import FilterStatus, SafetyFilter, Slack
from torchcbf.sim import Trajectory, simulate

F64 = torch.float64


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():  # closed loops need no graph (the filter would build one)
        yield


def _starts(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Starts on a ring of radius 2.5..3.5 around the obstacle; goals roughly opposite, so
    that the straight line crosses the unit ball at the origin."""
    gen = torch.Generator().manual_seed(seed)
    ang = 2 * math.pi * torch.rand(count, generator=gen, dtype=F64)
    rad = 2.5 + torch.rand(count, generator=gen, dtype=F64)
    start = torch.stack([rad * ang.cos(), rad * ang.sin()], -1)
    off = 0.4 * (torch.rand(count, generator=gen, dtype=F64) - 0.5)
    goal = -3.0 * torch.stack([(ang + off).cos(), (ang + off).sin()], -1)
    return start, goal


def _min_h(ball: Ball, x: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return ball(x).amin(-1)  # [B]


def _check_invariance(
    dyn: ControlAffine,
    ball: Ball,
    x0: torch.Tensor,
    nominal: Callable[[torch.Tensor, float], torch.Tensor],
    steps: int,
) -> Trajectory:
    """Filtered closed loop (alpha = 2, dt = 0.01) stays safe with every QP solved, while
    most of the unfiltered runs collide; returns the filtered run."""
    filt = SafetyFilter(dyn, ball, alpha=2.0).double()
    run = simulate(dyn, x0, steps, 0.01, nominal=nominal, safety_filter=filt, progress=False)
    assert not run.failed.any()
    assert _min_h(ball, run.x).min() >= -1e-6
    assert (run.status == FilterStatus.SOLVED).all()
    free = simulate(dyn, x0, steps, 0.01, nominal=nominal, progress=False)
    assert (_min_h(ball, free.x) < 0).double().mean() > 0.8  # without the filter most collide
    return run


def _single_integrator_invariance(count: int, steps: int) -> None:
    dyn = SingleIntegrator(2, u_min=-2.0, u_max=2.0).double()
    ball = Ball([0.0, 0.0], 1.0).double()
    x0, goal = _starts(count, seed=0)
    nominal = lambda x, t: (2.0 * (goal - x)).clamp(-2.0, 2.0)  # noqa: E731
    run = _check_invariance(dyn, ball, x0, nominal, steps)
    # the filter is minimally invasive: the robots still make progress toward their goals
    progress = (x0 - goal).norm(dim=-1) - (run.x[:, -1] - goal).norm(dim=-1)
    assert progress.median() > 1.0


def _unicycle_invariance(count: int, steps: int) -> None:
    dyn = Unicycle(u_min=torch.tensor([-1.0, -4.0]), u_max=torch.tensor([1.0, 4.0])).double()
    ball = Ball([0.0, 0.0], 1.0).double()
    p0, goal = _starts(count, seed=1)
    heading = torch.atan2(goal[:, 1] - p0[:, 1], goal[:, 0] - p0[:, 0])
    x0 = torch.cat([p0, heading.unsqueeze(-1)], -1)

    def nominal(x: torch.Tensor, t: float) -> torch.Tensor:
        d = goal - x[:, :2]
        err = torch.atan2(d[:, 1], d[:, 0]) - x[:, 2]
        err = torch.atan2(err.sin(), err.cos())
        return torch.stack([d.norm(dim=-1).clamp_max(1.0), 4.0 * err], -1).clamp(-4.0, 4.0)

    # the plain ball works for the unicycle: L_g h = (2 (p - c) . (cos, sin), 0) and v = 0
    # always satisfies the condition on the safe set (0 >= -alpha h)
    _check_invariance(dyn, ball, x0, nominal, steps)


def test_single_integrator_invariance() -> None:
    _single_integrator_invariance(32, 200)


def test_unicycle_invariance() -> None:
    _unicycle_invariance(32, 250)


@pytest.mark.slow
def test_invariance_1000_states() -> None:
    _single_integrator_invariance(1000, 300)
    _unicycle_invariance(1000, 400)


def test_robust_filter_against_worst_case_disturbance() -> None:
    w_max = 0.5
    dyn = SingleIntegrator(2, u_min=-3.0, u_max=3.0, disturbance_bound=w_max).double()
    ball = Ball([0.0, 0.0], 1.0).double()
    x0, goal = _starts(16, seed=2)
    nominal = lambda x, t: (2.0 * (goal - x)).clamp(-2.0, 2.0)  # noqa: E731

    def adversary(x: torch.Tensor, t: float) -> torch.Tensor:
        # w = -w_max sign(dh/dx M): pushes h down as hard as the bound allows
        return -w_max * torch.sign(2 * x)

    runs = {}
    for mode in ("robust", "vanilla"):
        filt = SafetyFilter(dyn, ball, mode=mode, alpha=2.0).double()
        runs[mode] = simulate(
            dyn,
            x0,
            80,
            0.02,
            nominal=nominal,
            safety_filter=filt,
            disturbance=adversary,
            progress=False,
        )
    assert _min_h(ball, runs["robust"].x).min() >= -1e-6
    assert (_min_h(ball, runs["vanilla"].x) < -1e-3).double().mean() > 0.8


def _double_integrator_clf(goal: list[float]) -> QuadraticLyapunov:
    # V = e' P e with e = (p - goal, v): a CLF of the double integrator (P from a PD law)
    eye = torch.eye(2, dtype=F64)
    P = torch.cat([torch.cat([eye, 0.5 * eye], 1), torch.cat([0.5 * eye, eye], 1)], 0)
    return QuadraticLyapunov(torch.tensor([*goal, 0.0, 0.0], dtype=F64), P, index=(0, 1, 2, 3))


def test_clf_drives_double_integrator_to_goal() -> None:
    dyn = DoubleIntegrator(2, u_min=-2.0, u_max=2.0).double()
    clf = _double_integrator_clf([1.0, -2.0])
    filt = SafetyFilter(dyn, lyapunovs=clf, clf_rate=1.0, slack=Slack(clf_weight=1e4)).double()
    gen = torch.Generator().manual_seed(3)
    x0 = torch.cat([4 * torch.rand(16, 2, generator=gen, dtype=F64) - 2, torch.zeros(16, 2)], -1)
    zero = lambda x, t: torch.zeros_like(x[:, :2])  # noqa: E731
    run = simulate(dyn, x0, 200, 0.05, nominal=zero, safety_filter=filt, progress=False)
    err = (run.x[:, -1, :2] - torch.tensor([1.0, -2.0], dtype=F64)).norm(dim=-1)
    assert err.max() < 0.05, err
    assert run.x[:, -1, 2:].norm(dim=-1).max() < 0.05


def test_cbf_clf_reaches_goal_around_obstacle() -> None:
    dyn = DoubleIntegrator(2, u_min=-4.0, u_max=4.0).double()
    ball = Ball([0.0, 0.0], 1.0).double()
    hocbf = rectify(ball, dyn, "high_order", gains=2.0)  # relative degree 2 -> 1
    goal = [3.0, 0.3]
    filt = SafetyFilter(dyn, hocbf, _double_integrator_clf(goal), alpha=2.0, clf_rate=1.0).double()
    x0 = torch.tensor(
        [[-3.0, 0.0, 0.0, 0.0], [-3.0, -0.4, 0.0, 0.0], [-2.5, 0.5, 0.5, 0.0]], dtype=F64
    )
    zero = lambda x, t: torch.zeros_like(x[:, :2])  # noqa: E731
    run = simulate(dyn, x0, 400, 0.03, nominal=zero, safety_filter=filt, progress=False)
    assert _min_h(ball, run.x).min() >= -1e-6
    err = (run.x[:, -1, :2] - torch.tensor(goal, dtype=F64)).norm(dim=-1)
    assert err.max() < 0.1, err
    # the straight line is blocked: the plain CLF alone goes through the obstacle
    clf_only = SafetyFilter(dyn, lyapunovs=_double_integrator_clf(goal), clf_rate=1.0).double()
    free = simulate(dyn, x0, 100, 0.03, nominal=zero, safety_filter=clf_only, progress=False)
    assert (_min_h(ball, free.x) < 0).any()
