"""Scenario B of SCENARIOS.md: MPPI vs stochastic CBF vs MPPI + stochastic CBF on a noisy
unicycle with acceleration input, among five elliptical obstacles.

Methods: ``"scbf"`` (stochastic CBF-QP on the proportional controller), ``"mppi"`` (MPPI
alone) and ``"mppi_scbf"`` (MPPI's first control filtered by the stochastic CBF-QP).

Choices left open by the paper, made here:
- MPPI's control noise covariance is ``diag(4, 4)`` (as scenario A); its plan starts at zero.
- The planner replans every ``planner_every`` loop steps (default 2: once per rollout step
  of 0.02 s); between replans the loop follows the plan.
- No control limits (the paper gives none), so the CBF-QP is feasible wherever the
  barriers' ``L_g h`` rows are.
- Each ellipse is rectified in exponential form ``h_e = L_f b + k b`` with ``k = 2``
  (pole at -2); the stochastic condition uses alpha = 1, beta = 1 on ``h_e``.
- Scenario ``b`` uses noise seed ``seed + b`` and MPPI seed ``seed + b``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcbf.barriers import Ellipse, rectify
from torchcbf.dynamics import AccelUnicycle
from torchcbf.filters import FilterStatus, SafetyFilter
from torchcbf.mppi import MPPI, QuadraticGoal, RolloutCost, SumCost
from torchcbf.scenarios.base import Scenario
from torchcbf.sim import Goal

METHODS = ("scbf", "mppi", "mppi_scbf")
GOAL = (2.0, 4.0)
CENTERS = ((1.0, 2.0), (3.0, 2.0), (2.0, 5.0), (-1.0, 1.0), (0.5, -1.0))
AXES = ((0.5, 1.5), (0.75, 2.0), (2.0, 0.25), (1.0, 0.75), (0.75, 0.5))
SIGMA = 0.28


def obstacles() -> Ellipse:
    """The five ellipses as one barrier ``b(x) -> [..., 5]`` on the position ``(x, y)``."""
    return Ellipse(torch.tensor(CENTERS), torch.tensor(AXES), index=(0, 1))


def proportional_controller(goal: tuple[float, float] = GOAL):
    """``v_d = min(2, |p - goal|)``, ``a = v_d - v``, ``omega = 10 wrap(heading - theta)``."""

    def control(x: Tensor, t: float) -> Tensor:
        d = x.new_tensor(goal) - x[..., :2]
        heading = torch.atan2(d[..., 1], d[..., 0])
        err = torch.remainder(heading - x[..., 3] + math.pi, 2 * math.pi) - math.pi
        v_d = d.norm(dim=-1).clamp(max=2.0)
        return torch.stack([v_d - x[..., 2], 10.0 * err], -1)

    return control


def mppi_cbf(
    method: str = "mppi_scbf",
    num_seeds: int = 32,
    num_samples: int = 20_000,
    horizon: int = 80,
    seed: int = 0,
    planner_every: int = 2,
    rectify_gain: float = 2.0,
    noise_sigma: float = 4.0,
    control_limit: float | None = None,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
) -> Scenario:
    """Build scenario B with one of :data:`METHODS` for ``num_seeds`` noise seeds."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    dt, steps = 0.01, 500
    limits = {}
    if control_limit is not None:
        limits = {"u_min": [-control_limit] * 2, "u_max": [control_limit] * 2}
    plant = AccelUnicycle(sigma=SIGMA, **limits).to(device=device, dtype=dtype)
    nominal_model = AccelUnicycle(**limits).to(device=device, dtype=dtype)
    ellipses = obstacles().to(device=device, dtype=dtype)

    planner = None
    if method in ("mppi", "mppi_scbf"):
        cost = SumCost(
            QuadraticGoal(GOAL, weight=2.0, index=(0, 1), terminal_weight=10.0),
            _InverseBarriers(ellipses, weight=2.0, eps=0.01),
        )
        planner = MPPI(
            nominal_model,
            cost,
            horizon=horizon,
            num_samples=num_samples,
            dt=0.02,
            noise_sigma=noise_sigma * torch.eye(2),
            temperature=0.03,
            control_cost_weight=0.1,
            seed=seed,
            keep_rollouts=min(512, num_samples),
        ).to(device=device, dtype=dtype)

    safety_filter = None
    if method in ("scbf", "mppi_scbf"):
        rectified = rectify(ellipses, nominal_model, form="exponential", gains=[rectify_gain])
        safety_filter = SafetyFilter(
            plant, barriers=[rectified], mode="stochastic", alpha=1.0, beta=1.0
        ).to(device=device, dtype=dtype)

    x0 = torch.tensor([0.0, 0.0, 0.0, math.pi / 4], device=device, dtype=dtype).repeat(num_seeds, 1)
    goal_region = Goal(GOAL, 0.25, deadline=5.0)
    return Scenario(
        name=f"mppi-cbf/{method}",
        dynamics=plant,
        x0=x0,
        steps=steps,
        dt=dt,
        seeds=torch.arange(seed, seed + num_seeds),
        planner=planner,
        nominal=proportional_controller() if method == "scbf" else None,
        safety_filter=safety_filter,
        integrator="euler_maruyama",
        planner_every=planner_every,
        barriers=[ellipses],
        goals=[goal_region],
        metric_goals=[goal_region],
        status_names={int(s): s.name.lower() for s in FilterStatus},
        snapshot_steps=(100,) if planner is not None else (),
    )


class _InverseBarriers(RolloutCost):
    """``sum_i weight / max(b_i(x), eps)`` per step over the outputs of one barrier."""

    def __init__(self, barrier: torch.nn.Module, weight: float, eps: float) -> None:
        super().__init__()
        self.barrier, self.weight, self.eps = barrier, weight, eps

    def stage(self, states: Tensor, controls: Tensor | None) -> Tensor:
        return (self.weight / self.barrier(states).clamp_min(self.eps)).sum(-1)
