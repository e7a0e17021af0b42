"""Rollout costs: values against explicit per-step loops."""

from __future__ import annotations

import math

import pytest
import torch

from torchcbf.barriers import Ball
from torchcbf.mppi import (
    BarrierCost,
    DiscreteBarrierCost,
    ObstacleCost,
    QuadraticGoal,
    StageCost,
    SumCost,
)


def _tol(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 1e-4


def _close(a: torch.Tensor, b: torch.Tensor, dtype: torch.dtype) -> None:
    torch.testing.assert_close(a, b, atol=_tol(dtype), rtol=_tol(dtype))


def _rollouts(device, dtype, B=2, K=3, H=4, n=3, m=2):
    g = torch.Generator().manual_seed(0)
    states = torch.randn(B, K, H + 1, n, generator=g, dtype=torch.float64).to(device, dtype)
    controls = torch.randn(B, K, H, m, generator=g, dtype=torch.float64).to(device, dtype)
    return states, controls, torch.zeros(B, device=device, dtype=dtype)


def _ellipse(x: torch.Tensor) -> torch.Tensor:
    return ((x[..., 0] - 0.5) / 2.0) ** 2 + ((x[..., 1] + 0.2) / 0.5) ** 2 - 1.0


def test_stage_cost_matches_loop(device, dtype):
    states, controls, t0 = _rollouts(device, dtype)
    stage = lambda x, u: (x**2).sum(-1) + 0.5 * (u**2).sum(-1)  # noqa: E731
    terminal = lambda x: 3.0 * x[..., 0] ** 2  # noqa: E731
    got = StageCost(stage, terminal)(states, controls, t0)
    B, K, H1, _ = states.shape
    want = torch.zeros(B, K, device=device, dtype=dtype)
    for j in range(H1 - 1):  # stage(x_{j+1}, u_j)
        want += stage(states[:, :, j + 1], controls[:, :, j])
    want += terminal(states[:, :, -1])
    assert got.shape == (B, K)
    _close(got, want, dtype)


def test_standard_costs_analytic(device, dtype):
    states, controls, t0 = _rollouts(device, dtype)
    p = states[..., 1:, :2]
    goal = QuadraticGoal((1.0, -1.0), weight=2.0, index=(0, 1), terminal_weight=10.0).to(device)
    d2 = ((p - torch.tensor([1.0, -1.0], device=device, dtype=dtype)) ** 2).sum(-1)
    want = 2.0 * d2.sum(-1) + 10.0 * d2[..., -1]
    _close(goal(states, controls, t0), want, dtype)

    obst = ObstacleCost((0.2, 0.1), radius=0.6, k_o=0.3, eps=0.01).to(device)
    dist = ((p - torch.tensor([0.2, 0.1], device=device, dtype=dtype)) ** 2).sum(-1).sqrt()
    want_o = (0.3 / torch.clamp(dist - 0.6, min=0.01)).sum(-1)
    torch.testing.assert_close(
        obst(states, controls, t0), want_o, atol=_tol(dtype), rtol=_tol(dtype)
    )

    bar = BarrierCost(_ellipse, weight=2.0, eps=0.01)
    want_b = (2.0 / torch.clamp(_ellipse(states[..., 1:, :]), min=0.01)).sum(-1)
    torch.testing.assert_close(
        bar(states, controls, t0), want_b, atol=_tol(dtype), rtol=_tol(dtype)
    )

    total = SumCost(goal, obst, bar)
    torch.testing.assert_close(
        total(states, controls, t0), want + want_o + want_b, atol=_tol(dtype), rtol=_tol(dtype)
    )
    # "+" builds the same sum; plain rollout-level callables are summed as well, also
    # inside a sum that is a term of another
    plain = lambda s, u, t: s[..., 0].sum(-1)  # noqa: E731
    nested = (goal + plain) + obst
    torch.testing.assert_close(
        nested(states, controls, t0),
        want + want_o + states[..., 0].sum(-1),
        atol=_tol(dtype),
        rtol=_tol(dtype),
    )
    combined = goal + obst + plain
    torch.testing.assert_close(
        combined(states, controls, t0),
        want + want_o + states[..., 0].sum(-1),
        atol=_tol(dtype),
        rtol=_tol(dtype),
    )


def test_nonadjacent_index():
    states = torch.randn(1, 2, 3, 4, dtype=torch.float64)
    cost = QuadraticGoal((1.0, 2.0), index=(3, 1))
    p = states[..., 1:, [3, 1]]
    want = ((p - torch.tensor([1.0, 2.0], dtype=torch.float64)) ** 2).sum(-1).sum(-1)
    torch.testing.assert_close(cost(states, None), want)


def test_bad_costs():
    with pytest.raises(ValueError, match="index"):
        QuadraticGoal((1.0, 2.0), index=(0, 1, 2))
    with pytest.raises(ValueError, match="eps"):
        ObstacleCost((0.0, 0.0), 1.0, eps=0.0)
    with pytest.raises(TypeError, match="barrier"):
        BarrierCost(3.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="stage"):
        StageCost(None)  # type: ignore[arg-type]
    # a weight that is not a finite number >= 0 (every sample's cost NaN, or a barrier that
    # attracts) is refused by every barrier term
    ball = Ball([0.0, 0.0], 0.5)
    for bad in (math.nan, math.inf, -5.0):
        for make in (
            lambda w: ObstacleCost((0.0, 0.0), 1.0, k_o=w),
            lambda w: BarrierCost(ball, weight=w),
            lambda w: DiscreteBarrierCost(ball, gamma=0.5, weight=w),
        ):
            with pytest.raises(ValueError, match=r"(k_o|weight) must be a finite number >= 0"):
                make(bad)


def _moving_barriers(device, dtype):
    """A Ball with a velocity and a MovingBall on a curved path, with ``h(x, t)`` by hand."""
    from torchcbf.barriers import Ball, MovingBall

    def path(t: torch.Tensor) -> torch.Tensor:
        return torch.stack([0.3 * t, torch.sin(t)], -1)

    ball = Ball([0.1, -0.2], 0.4, velocity=[0.5, -1.0]).to(device, dtype)
    moving = MovingBall(path, 0.3).to(device, dtype)
    c0 = torch.tensor([0.1, -0.2], dtype=torch.float64)
    v = torch.tensor([0.5, -1.0], dtype=torch.float64)

    def ball_h(x, t):
        c = c0.to(x) + v.to(x) * t[..., None]
        return ((x[..., :2] - c) ** 2).sum(-1) - 0.4**2

    def moving_h(x, t):
        return ((x[..., :2] - path(t)) ** 2).sum(-1) - 0.3**2

    return [(ball, ball_h), (moving, moving_h)]


def test_barrier_costs_read_a_time_varying_barrier_at_each_state_time(device, dtype):
    """Rollout state k is at t0 + k dt: each barrier cost, and Avoid's cost and robustness,
    against a per-step loop over hand-written h(x, t)."""
    from torchcbf.mppi import Avoid, DiscreteBarrierCost

    states, controls, _ = _rollouts(device, dtype, B=2, K=3, H=5)
    t0 = torch.tensor([0.4, 2.0], device=device, dtype=dtype)
    dt = 0.3
    B, K, T, _ = states.shape
    for barrier, h_of in _moving_barriers(device, dtype):
        h = torch.stack([h_of(states[:, :, k], (t0 + k * dt)[:, None]) for k in range(T)], -1)
        want = (2.0 / h[..., 1:].clamp_min(0.01)).sum(-1)
        cost = BarrierCost(barrier, weight=2.0)
        assert cost.needs_time
        _close(cost(states, controls, t0, dt=dt), want, dtype)
        goal = QuadraticGoal([1.0, 0.0], index=(0, 1))
        total = goal + cost
        assert total.needs_time and cost in total.whole_terms
        _close(total(states, controls, t0, dt=dt), goal(states, controls, t0) + want, dtype)

        disc = DiscreteBarrierCost(barrier, gamma=0.2, weight=3.0, steps=3)
        viol = torch.relu(0.8 * h[..., :3] - h[..., 1:4]).sum(-1)
        _close(disc(states, controls, t0, dt=dt), 3.0 * viol, dtype)

        avoid = Avoid(barrier=barrier, weight=0.5, interval=(0.9, 2.7))
        times = t0[:, None] + dt * torch.arange(T, device=device, dtype=dtype)
        inside = ((times >= 0.9 - 1e-5) & (times <= 2.7 + 1e-5))[:, None].expand(B, K, T)
        worst = h.masked_fill(~inside, float("inf")).amin(-1)
        want_a = torch.where(inside.any(-1), 0.5 / worst.clamp_min(0.01), torch.zeros_like(worst))
        _close(avoid(states, controls, t0, dt=dt), want_a, dtype)
        times_k = times[:, None].expand(B, K, T)
        _close(avoid.robustness(states, times_k), worst, dtype)


@pytest.mark.parametrize("kind", ["BarrierCost", "DiscreteBarrierCost", "Avoid"])
def test_a_time_varying_barrier_without_times_is_refused(kind: str) -> None:
    """Where a barrier cost has no times (a call without dt=, BarrierCost.stage,
    Avoid.predicate) a moving obstacle would be read at t = 0: it is refused, also for a
    ball made time-varying after the cost was built."""
    from torchcbf.barriers import Ball
    from torchcbf.mppi import Avoid, DiscreteBarrierCost

    build = {
        "BarrierCost": lambda b: BarrierCost(b),
        "DiscreteBarrierCost": lambda b: DiscreteBarrierCost(b, gamma=0.1),
        "Avoid": lambda b: Avoid(barrier=b),
    }[kind]
    ball = Ball([0.0, 0.0], 0.5)
    cost = build(ball)
    states, controls = torch.ones(1, 3, 5, 2), torch.zeros(1, 3, 4, 2)
    t0 = torch.zeros(1)
    assert cost(states, controls, t0, dt=0.1).shape == (1, 3)
    if kind != "Avoid":
        assert not cost.needs_time
        assert cost(states, controls, t0).shape == (1, 3)
    ball.velocity = torch.tensor([1.0, 0.0])
    if kind != "Avoid":
        assert cost.needs_time
    with pytest.raises(ValueError, match="dt="):
        cost(states, controls, t0)
    untimed = {
        "BarrierCost": lambda: cost.stage(states, None),
        "DiscreteBarrierCost": None,
        "Avoid": lambda: cost.predicate(states),
    }[kind]
    if untimed is not None:
        with pytest.raises(ValueError, match="time-varying"):
            untimed()


def test_a_sum_scores_the_terms_it_holds_now():
    """A term replaced in or appended to ``SumCost.terms`` is scored, also by the planner's
    fused kernel, as a sum built with it."""
    from torchcbf import MPPI, SingleIntegrator

    states, controls, t0 = _rollouts("cpu", torch.float64, n=2)
    cost = QuadraticGoal([1.0, 1.0]) + ObstacleCost([0.5, 0.0], 0.2)
    cost.terms[0] = QuadraticGoal([-3.0, 2.0])
    fresh = QuadraticGoal([-3.0, 2.0]) + ObstacleCost([0.5, 0.0], 0.2)
    _close(cost(states, controls, t0), fresh(states, controls, t0), torch.float64)
    extra = QuadraticGoal([5.0, 5.0], weight=100.0)
    cost.terms.append(extra)
    _close(cost(states, controls, t0), (fresh + extra)(states, controls, t0), torch.float64)

    plans = {}
    for backend in ("auto", "torch"):
        built = QuadraticGoal([1.0, 1.0]) + ObstacleCost([0.5, 0.0], 0.2)
        planner = MPPI(SingleIntegrator(2), built, 10, 64, 0.1, 4.0, 0.1, seed=0, backend=backend)
        planner(torch.zeros(2))
        built.terms[0] = QuadraticGoal([-20.0, 15.0])
        plans[backend] = planner(torch.zeros(2)).u
        assert planner.path == ("torch" if backend == "torch" else "fused")
    torch.testing.assert_close(plans["auto"], plans["torch"], atol=1e-5, rtol=1e-5)
    assert plans["auto"][0] < 0.0  # towards the new goal, behind the start
