"""Scenario A (docs/scenarios.md): timed reach-avoid with MPPI on a single integrator.

"Reach g1 between 0 and 3.5 s, g2 between 3.6 and 5 s, and g3 between 5.1 and 10 s, while
avoiding the obstacle." The planner's cost is the specification itself (negated robustness
with the paper's goal and obstacle costs), reading the executed history so a goal reached
inside its window is not revisited.

Choices left open by the paper, made here: the plant is integrated exactly (a single
integrator under a zero-order hold), the planner runs at every step (dt = 0.1 s) with its
rollouts on the same dt, scenario ``b`` of a batch uses MPPI seed ``seed + b``, and the
sample costs are normalised by their standard deviation before the exponent
(``cost_normalization="std"``): with temperature 0.03 the plain exponent is nearly greedy.
"""

from __future__ import annotations

import torch

from torchcbf.dynamics import SingleIntegrator
from torchcbf.mppi import MPPI, And, Avoid, Reach
from torchcbf.scenarios.base import Scenario

GOALS = (
    ((4.0, 4.0), (0.0, 3.5), 10.0),
    ((6.0, 9.0), (3.6, 5.0), 2.0),
    ((4.0, 1.0), (5.1, 10.0), 1.0),
)
GOAL_RADIUS = 0.5
OBSTACLE_CENTER, OBSTACLE_RADIUS = (3.0, 3.0), 0.6


def reach_avoid_spec() -> And:
    """``G(avoid) AND F[0,3.5](g1) AND F[3.6,5](g2) AND F[5.1,10](g3)`` with the paper's costs."""
    avoid = Avoid(OBSTACLE_CENTER, OBSTACLE_RADIUS, weight=0.3, eps=0.01)
    reaches = [Reach(c, GOAL_RADIUS, interval=w, weight=k) for c, w, k in GOALS]
    return And(avoid, *reaches)


def reach_avoid(
    num_seeds: int = 10,
    num_samples: int = 10_000,
    horizon: int = 50,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
) -> Scenario:
    """Build scenario A for ``num_seeds`` seeds planned as one batch of environments."""
    dt, steps = 0.1, 100
    dynamics = SingleIntegrator(2, u_min=-5.0, u_max=5.0).to(device=device, dtype=dtype)
    spec = reach_avoid_spec().to(device=device, dtype=dtype)
    planner = MPPI(
        dynamics,
        spec,
        horizon=horizon,
        num_samples=num_samples,
        dt=dt,
        noise_sigma=4.0 * torch.eye(2),
        temperature=0.03,
        control_cost_weight=0.1,
        seed=seed,
        cost_normalization="std",
        keep_rollouts=min(512, num_samples),
    ).to(device=device, dtype=dtype)
    x0 = torch.zeros(num_seeds, 2, device=device, dtype=dtype)
    avoid = spec.specs[0]

    def obstacle(x: torch.Tensor) -> torch.Tensor:
        return avoid.predicate(x)

    return Scenario(
        name="reach-avoid",
        dynamics=dynamics,
        x0=x0,
        steps=steps,
        dt=dt,
        seeds=torch.arange(seed, seed + num_seeds),
        planner=planner,
        integrator="rk4",
        barriers=[obstacle],
        goals=[s for s in spec.specs[1:]],
        spec=spec,
        snapshot_steps=(20,),
    )
