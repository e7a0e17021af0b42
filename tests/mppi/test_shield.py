"""ShieldMPPI, MPPI.correct and DiscreteBarrierCost against hand-written references."""

from __future__ import annotations

import pytest
import torch
from _devices import device_matches_cpu

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
    for bad_steps, error in (
        (0, ValueError),
        (-2, ValueError),
        (1.5, TypeError),
        (True, TypeError),
    ):
        with pytest.raises(error, match="steps"):
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
    assert torch.equal(out.filtered.u, out.u) and out.filtered.status.shape == (2,)
    assert torch.equal(out.filtered.status, filt(x, raw.u, 0.0).status)
    assert raw.filtered is None
    assert shield(x[0], 0.0).filtered.status.shape == ()  # one state: the filter's own shape
    assert shield.dt == planner.dt
    with pytest.raises(TypeError, match="planner"):
        ShieldMPPI(filt, filt)  # type: ignore[arg-type]
    # a NumPy state is refused before the planner advances (no unfiltered control left)
    before = planner._plan.clone()
    with pytest.raises(TypeError, match="x must be a torch.Tensor"):
        shield(x.numpy(), 0.0)
    assert torch.equal(planner._plan, before)


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


# -- on the device fixture's device ------------------------------------------------------------


@pytest.mark.parametrize("steps", [None, 3])
def test_barrier_costs_and_gradients_on_device_equal_cpu(dtype, device, steps) -> None:
    """Both barrier costs of rollouts drawn on the CPU, and their gradients to the states,
    on the device equal the CPU's."""
    gen = torch.Generator().manual_seed(2)
    states = 2.0 * torch.randn(3, 5, 7, 2, generator=gen, dtype=torch.float64)
    centers, axes = [[1.0, 0.0], [0.0, 2.0]], [[0.5, 1.0], [1.0, 0.3]]

    def run(dev: torch.device):
        ellipses = Ellipse(torch.tensor(centers), torch.tensor(axes)).to(device=dev, dtype=dtype)
        balls = Ball(torch.tensor(centers), torch.tensor([0.5, 0.3])).to(device=dev, dtype=dtype)
        x = states.to(device=dev, dtype=dtype).requires_grad_()
        discrete = DiscreteBarrierCost(ellipses, gamma=0.3, weight=7.0, steps=steps)(
            x, x[..., :6, :]
        )
        smooth = BarrierCost(balls, weight=2.0, eps=0.01)(x, x[..., :6, :])
        grads = torch.autograd.grad((discrete + smooth).sum(), x)
        return discrete.detach(), smooth.detach(), grads[0]

    discrete, smooth, grad = device_matches_cpu(run, device, dtype)
    assert bool((discrete > 0).any()) and bool((grad != 0).any())


def _shielded(device: torch.device, dtype: torch.dtype, *, in_loop: bool = False, seed: int = 0):
    dyn = SingleIntegrator(2).to(device=device, dtype=dtype)
    ball = Ball([1.0, 0.0], 0.5).to(device=device, dtype=dtype)
    filt = SafetyFilter(dyn, [ball], alpha=1.0).to(device=device, dtype=dtype)
    cost = SumCost(
        QuadraticGoal([2.0, 0.0], weight=1.0), DiscreteBarrierCost(ball, gamma=0.2, weight=1e3)
    )
    planner = MPPI(dyn, cost, horizon=6, num_samples=64, dt=0.1, noise_sigma=1.0,
                   temperature=0.1, seed=seed).to(device=device, dtype=dtype)  # fmt: skip
    return ShieldMPPI(planner, filt, in_loop=in_loop), filt


def test_shield_on_device_filters_and_feeds_back_over_calls(dtype, device) -> None:
    """On the device, each call's control is the filter's answer to the control of an
    unshielded planner with the same seed that was corrected the same way, the plan starts
    with it and the planner keeps it, over calls that shift the corrected plan."""
    shield, filt = _shielded(device, dtype)
    reference, _ = _shielded(device, dtype)
    x = torch.tensor([[0.45, 0.0], [-1.0, 0.5], [0.4, 0.1]], dtype=torch.float64)
    x = x.to(device=device, dtype=dtype)
    tol = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-5}
    for k in range(3):
        out = shield(x, 0.1 * k)
        raw = reference.planner(x, 0.1 * k)
        expected = filt(x, raw.u, 0.1 * k).u
        reference.planner.correct(expected)
        assert out.u.device.type == device.type
        torch.testing.assert_close(out.u, expected, **tol)
        torch.testing.assert_close(out.plan[:, 0], expected, **tol)
        torch.testing.assert_close(out.plan[:, 1:], raw.plan[:, 1:], **tol)
        torch.testing.assert_close(shield.planner._plan, reference.planner._plan, **tol)
        x = x + 0.1 * out.u
    assert not torch.equal(raw.u, expected)  # the filter changed the control


def test_loop_filter_of_given_controls_on_device_equals_cpu(dtype, device) -> None:
    """An in-loop shield's filter, given controls drawn on the CPU, gives the CPU's filtered
    controls, statuses and barrier values on the device and writes them into the plan."""
    x = torch.tensor([[0.45, 0.0], [-1.0, 0.5], [0.52, -0.2], [2.0, 2.0]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.0], [0.5, -0.5], [-2.0, 0.3], [0.0, 0.0]], dtype=torch.float64)

    def run(dev: torch.device):
        shield, _ = _shielded(dev, dtype, in_loop=True)
        f = {"device": dev, "dtype": dtype}
        out = shield(x.to(**f), 0.0)
        filtered = shield.loop_filter(x.to(**f), u.to(**f), 0.0)
        return filtered.u, filtered.status, filtered.h, out.plan[:, 0], shield.planner._plan[:, 0]

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    u_f, status, h, plan0, kept = device_matches_cpu(run, device, dtype, **loose)
    assert torch.equal(plan0, u_f) and torch.equal(kept, u_f)
    assert not torch.equal(u_f.cpu(), u.to(dtype))  # the filter acted on some row
