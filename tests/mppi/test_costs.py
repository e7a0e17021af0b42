"""Rollout costs: values against explicit per-step loops."""

from __future__ import annotations

import pytest
import torch

from torchcbf.mppi import BarrierCost, ObstacleCost, QuadraticGoal, StageCost, SumCost


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
    # "+" builds the same sum; plain rollout-level callables are summed as well
    plain = lambda s, u, t: s[..., 0].sum(-1)  # noqa: E731
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


@pytest.mark.parametrize("kind", ["BarrierCost", "DiscreteBarrierCost", "Avoid"])
def test_a_time_varying_barrier_in_a_cost_without_time_is_refused(kind: str) -> None:
    """These costs evaluate b(x) without the rollout's times: a moving obstacle would be read
    at t = 0, so it is refused at construction and, made time-varying later, at the call."""
    from torchcbf.barriers import Ball, MovingBall
    from torchcbf.mppi import Avoid, DiscreteBarrierCost

    build = {
        "BarrierCost": lambda b: BarrierCost(b),
        "DiscreteBarrierCost": lambda b: DiscreteBarrierCost(b, gamma=0.1),
        "Avoid": lambda b: Avoid(barrier=b),
    }[kind]
    moving = MovingBall(lambda t: torch.stack([t, torch.zeros_like(t)], -1), 0.5)
    for barrier in (moving, Ball([0.0, 0.0], 0.5, velocity=[1.0, 0.0])):
        with pytest.raises(ValueError, match="time-varying"):
            build(barrier)
    ball = Ball([0.0, 0.0], 0.5)
    cost = build(ball)
    states, controls = torch.ones(1, 3, 5, 2), torch.zeros(1, 3, 4, 2)
    t0 = torch.zeros(1)
    call = (
        (lambda: cost(states, controls, t0, dt=0.1))
        if kind == "Avoid"
        else (lambda: cost(states, controls, t0))
    )
    assert call().shape == (1, 3)
    ball.velocity = torch.tensor([1.0, 0.0])
    with pytest.raises(ValueError, match="time-varying"):
        call()
