"""ShieldMPPI, MPPI.correct and DiscreteBarrierCost against hand-written references."""

from __future__ import annotations

import pytest
import torch

from torchcbf.barriers import Ball, Ellipse
from torchcbf.dynamics import SingleIntegrator
from torchcbf.filters import SafetyFilter
from torchcbf.mppi import MPPI, BarrierCost, DiscreteBarrierCost, QuadraticGoal, ShieldMPPI, SumCost


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("steps", [None, 1, 3, 5, 9])
def test_discrete_barrier_cost_matches_a_loop(dtype: torch.dtype, steps: int | None) -> None:
    gen = torch.Generator().manual_seed(0)
    ellipses = Ellipse(
        torch.tensor([[1.0, 0.0], [0.0, 2.0]]), torch.tensor([[0.5, 1.0], [1.0, 0.3]])
    )
    ellipses = ellipses.to(dtype)
    states = torch.randn(2, 3, 6, 2, generator=gen, dtype=dtype) * 2
    term = DiscreteBarrierCost(ellipses, gamma=0.3, weight=7.0, steps=steps)
    cost = term(states, states[..., :5, :])
    expected = torch.zeros(2, 3, dtype=dtype)
    for b in range(2):
        for k in range(3):
            for j in range(min(5, steps or 5)):
                for i in range(2):
                    now = ellipses(states[b, k, j])[i]
                    nxt = ellipses(states[b, k, j + 1])[i]
                    expected[b, k] += 7.0 * max(0.7 * float(now) - float(nxt), 0.0)
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(cost, expected, rtol=tol, atol=tol)


def test_discrete_barrier_cost_one_output_barrier_and_errors() -> None:
    ball = Ball([0.0, 0.0], 1.0)
    states = torch.tensor([[[[2.0, 0.0], [1.5, 0.0], [1.5, 0.0]]]])  # b: 3, 1.25, 1.25
    cost = DiscreteBarrierCost(ball, gamma=0.5, weight=2.0)(states, states[..., :2, :])
    torch.testing.assert_close(cost, torch.tensor([[2.0 * (1.5 - 1.25)]]))
    for bad in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="gamma"):
            DiscreteBarrierCost(ball, gamma=bad, weight=1.0)
    with pytest.raises(ValueError, match="weight"):
        DiscreteBarrierCost(ball, gamma=0.5, weight=-1.0)
    for bad_steps in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="steps"):
            DiscreteBarrierCost(ball, gamma=0.5, steps=bad_steps)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="barrier"):
        DiscreteBarrierCost(3.0, gamma=0.5, weight=1.0)  # type: ignore[arg-type]


def test_barrier_cost_sums_the_outputs_of_a_multi_output_barrier() -> None:
    centers, radii = torch.tensor([[1.0, 0.0], [0.0, 2.0]]), torch.tensor([0.5, 0.3])
    stacked = BarrierCost(Ball(centers, radii), weight=2.0, eps=0.01)
    singles = [
        BarrierCost(Ball(c, r), weight=2.0, eps=0.01) for c, r in zip(centers, radii, strict=True)
    ]
    states = torch.randn(2, 4, 7, 2, generator=torch.Generator().manual_seed(1))
    controls = torch.zeros(2, 4, 6, 2)
    torch.testing.assert_close(
        stacked(states, controls), singles[0](states, controls) + singles[1](states, controls)
    )


def _planner(seed: int = 0) -> MPPI:
    cost = QuadraticGoal([2.0, 0.0], weight=1.0, terminal_weight=5.0)
    return MPPI(
        SingleIntegrator(2),
        cost,
        horizon=6,
        num_samples=64,
        dt=0.1,
        noise_sigma=1.0,
        temperature=0.1,
        seed=seed,
    ).double()


def test_correct_replaces_the_first_control_of_the_plan() -> None:
    planner = _planner()
    with pytest.raises(ValueError, match="call the planner first"):
        planner.correct(torch.zeros(2, dtype=torch.float64))
    x = torch.zeros(3, 2, dtype=torch.float64)
    out = planner(x)
    u = torch.tensor([[0.1, -0.2], [0.3, 0.4], [0.0, 0.0]], dtype=torch.float64)
    planner.correct(u)
    torch.testing.assert_close(planner._plan[:, 0], u)
    torch.testing.assert_close(planner._plan[:, 1:], out.plan[:, 1:])
    with pytest.raises(ValueError, match="u must have shape"):
        planner.correct(torch.zeros(2, 2, dtype=torch.float64))


def test_shield_mppi_filters_and_feeds_back() -> None:
    dyn = SingleIntegrator(2).double()
    ball = Ball([1.0, 0.0], 0.5).double()
    filt = SafetyFilter(dyn, [ball], alpha=1.0).double()
    cost = SumCost(
        QuadraticGoal([2.0, 0.0], weight=1.0), DiscreteBarrierCost(ball, gamma=0.2, weight=1e3)
    )
    planner = MPPI(
        dyn, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=1.0, temperature=0.1, seed=0
    ).double()
    reference = MPPI(
        dyn, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=1.0, temperature=0.1, seed=0
    ).double()
    shield = ShieldMPPI(planner, filt)
    x = torch.tensor([[0.45, 0.0], [-1.0, 0.5]], dtype=torch.float64)
    out = shield(x, 0.0)
    raw = reference(x, 0.0)
    expected = filt(x, raw.u, 0.0).u
    torch.testing.assert_close(out.u, expected)
    torch.testing.assert_close(out.plan[:, 0], expected)
    torch.testing.assert_close(out.plan[:, 1:], raw.plan[:, 1:])
    torch.testing.assert_close(planner._plan[:, 0], expected)
    assert shield.dt == planner.dt
    with pytest.raises(TypeError, match="planner"):
        ShieldMPPI(filt, filt)  # type: ignore[arg-type]


class _Counting:
    """A filter that counts its calls."""

    def __init__(self, inner: SafetyFilter) -> None:
        self.inner, self.calls = inner, 0

    def __call__(self, x: torch.Tensor, u: torch.Tensor, t: object) -> object:
        self.calls += 1
        return self.inner(x, u, t)


def test_in_loop_shield_filters_once_per_step_with_the_same_trajectory() -> None:
    from torchcbf.sim import simulate

    dyn = SingleIntegrator(2).double()
    ball = Ball([1.0, 0.0], 0.5).double()
    cost = SumCost(
        QuadraticGoal([2.0, 0.0], weight=1.0), DiscreteBarrierCost(ball, gamma=0.2, weight=1e3)
    )
    x0 = torch.tensor([[0.0, 0.05], [-1.0, 0.5]], dtype=torch.float64)
    runs = {}
    for in_loop in (False, True):
        filt = _Counting(SafetyFilter(dyn, [ball], alpha=1.0).double())
        planner = MPPI(dyn, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=1.0,
                       temperature=0.1, seed=0).double()  # fmt: skip
        shield = ShieldMPPI(planner, filt, in_loop=in_loop)
        loop_filter = shield.loop_filter if in_loop else filt
        traj = simulate(dyn, x0, steps=20, dt=0.05, planner=shield, safety_filter=loop_filter,
                        planner_every=2, integrator="euler", progress=False)  # fmt: skip
        runs[in_loop] = (traj, filt.calls)
    (before, calls_before), (after, calls_after) = runs[False], runs[True]
    assert calls_before == 20 + 10 and calls_after == 20
    # filtering the filtered control again returns it (up to the QP's tolerance)
    torch.testing.assert_close(after.x, before.x, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(after.u, before.u, rtol=1e-6, atol=1e-6)
    assert float(after.h.min()) >= -1e-9


def test_in_loop_shield_feeds_the_loop_filters_control_back() -> None:
    dyn = SingleIntegrator(2).double()
    ball = Ball([1.0, 0.0], 0.5).double()
    filt = SafetyFilter(dyn, [ball], alpha=1.0).double()
    shield = ShieldMPPI(_planner(), filt, in_loop=True)
    x = torch.tensor([[0.45, 0.0], [-1.0, 0.5]], dtype=torch.float64)
    out = shield(x, 0.0)
    raw_u = out.u.clone()
    filtered = shield.loop_filter(x, out.u, 0.0).u
    torch.testing.assert_close(out.plan[:, 0], filtered)
    torch.testing.assert_close(shield.planner._plan[:, 0], filtered)
    assert not torch.equal(raw_u, filtered)  # the first state needs the filter
    again = shield.loop_filter(x, raw_u, 0.0).u  # a later call leaves the plan alone
    torch.testing.assert_close(out.plan[:, 0], filtered)
    torch.testing.assert_close(again, filtered)
    assert shield.loop_filter.barriers is filt.barriers  # the filter's attributes read through
    with pytest.raises(ValueError, match="in_loop"):
        _ = ShieldMPPI(_planner(), filt).loop_filter
