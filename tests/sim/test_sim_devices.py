"""A stochastic closed loop with every part (planner every few steps, nominal, filter,
sensor, estimator, disturbance) and its metrics on the device fixture's device against the
CPU: the counter-based noise draws the same numbers on every device."""

from __future__ import annotations

from typing import NamedTuple

import torch
from _devices import device_matches_cpu
from _host_traffic import HostTraffic

from torchcbf.barriers import Ball, rectify
from torchcbf.dynamics import DoubleIntegrator
from torchcbf.estimation import EKF, GaussianSensor
from torchcbf.filters import SafetyFilter
from torchcbf.mppi import Reach
from torchcbf.sim import Goal, metrics, simulate

GOAL = (2.0, 0.2)


class _Plan(NamedTuple):
    u: torch.Tensor
    plan: torch.Tensor


class _Ramp:
    """A deterministic planner: a plan of 4 controls that ramp towards the goal."""

    dt = 0.1

    def __call__(self, x: torch.Tensor, t: float) -> _Plan:
        goal = torch.tensor(GOAL, device=x.device, dtype=x.dtype)
        u = (goal - x[:, :2] - x[:, 2:]).clamp(-1.0, 1.0)
        plan = (
            u.unsqueeze(1) * torch.linspace(1.0, 0.25, 4, device=x.device, dtype=x.dtype)[:, None]
        )
        return _Plan(plan[:, 0], plan)


def test_stochastic_loop_with_every_part_and_its_metrics_on_device_equal_cpu(dtype, device):
    gen = torch.Generator().manual_seed(0)
    x0 = torch.zeros(6, 4, dtype=torch.float64)
    x0[:, :2] = torch.tensor([-1.0, 0.0]) + 0.2 * torch.randn(
        6, 2, generator=gen, dtype=torch.float64
    )
    seeds = [11, 3, 5, 8, 13, 21]

    def run(dev: torch.device):
        f = {"device": dev, "dtype": dtype}
        dyn = DoubleIntegrator(dim=2, sigma=0.05, u_min=-1.5, u_max=1.5, disturbance_bound=0.1)
        ball = Ball([0.5, 0.0], 0.4, index=(0, 1))
        # rectified on the CPU: its relative-degree check draws sample states there
        barrier = rectify(ball, DoubleIntegrator(dim=2), form="high_order", gains=[2.0])
        dyn, barrier = dyn.to(**f), barrier.to(**f)
        filt = SafetyFilter(dyn, barrier, alpha=2.0, mode="robust").to(**f)
        sensor = GaussianSensor(C=torch.eye(4)[:2], std=0.02).to(**f)
        estimator = EKF(dyn, sensor)

        def nominal(x: torch.Tensor, t: float, u_plan: torch.Tensor) -> torch.Tensor:
            return u_plan - 0.5 * x[:, 2:]

        def disturbance(x: torch.Tensor, t: float) -> torch.Tensor:
            return 0.1 * torch.sin(3.0 * t + x)

        traj = simulate(dyn, x0.to(**f), 40, 0.05, planner=_Ramp(), nominal=nominal,
                        safety_filter=filt, sensor=sensor, estimator=estimator, seed=seeds,
                        planner_every=3, disturbance=disturbance, progress=False)  # fmt: skip
        spec = Reach(GOAL, 0.6, (0.0, 2.0)).to(dev)
        found = metrics(traj, barriers=[ball.to(**f)], goals=[Goal(GOAL, 0.6)], spec=spec)
        return traj.x, traj.x_hat, traj.u_nom, traj.u, traj.h, traj.status, traj.failed, found

    loose = {} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-4}
    x, x_hat, u_nom, u, h, status, failed, found = device_matches_cpu(run, device, dtype, **loose)
    assert not bool(failed.any()) and bool((x != x_hat).any())  # noisy estimates
    assert bool((u - u_nom).abs().amax() > 0.05)  # the filter acted
    assert set(found) >= {"collision", "min_h", "goal_reached", "spec_robustness"}


def test_loop_steps_make_no_host_traffic() -> None:
    """The steps of a loop with a planner every few steps, a nominal, a noisy sensor, process
    noise and a disturbance run on the meta device (no value is read back) and copy nothing
    from the host."""
    meta = torch.device("meta")
    dyn = DoubleIntegrator(dim=2, sigma=0.05, u_min=-1.5, u_max=1.5, disturbance_bound=0.1)
    dyn = dyn.to(meta)
    sensor = GaussianSensor(std=0.02, state_dim=4).to(meta)

    def nominal(x: torch.Tensor, t: float, u_plan: torch.Tensor) -> torch.Tensor:
        return u_plan - 0.5 * x[:, 2:]

    def disturbance(x: torch.Tensor, t: float) -> torch.Tensor:
        return torch.sin(x)

    class Plan:
        dt = 0.1

        def __call__(self, x: torch.Tensor, t: float) -> _Plan:
            plan = torch.zeros(x.shape[0], 4, 2, device=x.device, dtype=x.dtype)
            return _Plan(plan[:, 0], plan)

    with HostTraffic() as traffic:
        traj = simulate(dyn, torch.zeros(3, 4, device=meta), 5, 0.05, planner=Plan(),
                        nominal=nominal, sensor=sensor, seed=4, planner_every=2,
                        disturbance=disturbance, progress=False)  # fmt: skip
    assert not traffic.events, dict(traffic.events)
    assert traj.x.shape == (3, 6, 4) and traj.x.device.type == "meta"
