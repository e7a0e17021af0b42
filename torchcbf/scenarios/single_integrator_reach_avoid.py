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

from dataclasses import asdict, dataclass
from typing import Any

import torch

from torchcbf._checks import check_number, check_positive_int
from torchcbf.dynamics import SingleIntegrator
from torchcbf.mppi import MPPI, And, Avoid, Reach
from torchcbf.scenarios.base import Scenario
from torchcbf.scenarios.registry import Column, Dimension, EnvEntry, ScenarioEntry, register

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


@dataclass(frozen=True)
class ReachAvoidParams:
    """The parameters of scenario A.

    Attributes:
        num_samples, horizon: MPPI's ``K`` and ``H`` (the paper: 10,000 and 50).
        temperature: MPPI's temperature (on costs normalised by their standard deviation).
        noise_sigma: standard deviation of the sampled controls (per axis).
        control_cost_weight: weight of MPPI's control cost.
    """

    num_samples: int = 10_000
    horizon: int = 50
    temperature: float = 0.03
    noise_sigma: float = 4.0
    control_cost_weight: float = 0.1


def build(
    params: ReachAvoidParams,
    *,
    num_seeds: int = 10,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
) -> Scenario:
    """Scenario A with ``params`` for ``num_seeds`` seeds planned as one batch."""
    check_positive_int("num_seeds", num_seeds)
    check_positive_int("num_samples", params.num_samples)
    check_positive_int("horizon", params.horizon)
    for name in ("temperature", "noise_sigma"):
        check_number(name, getattr(params, name), low=0.0, strict=True)
    check_number("control_cost_weight", params.control_cost_weight, low=0.0)
    dtype = torch.float32 if dtype is None else dtype
    dt, steps = 0.1, 100
    dynamics = SingleIntegrator(2, u_min=-5.0, u_max=5.0).to(device=device, dtype=dtype)
    spec = reach_avoid_spec().to(device=device, dtype=dtype)
    planner = MPPI(
        dynamics,
        spec,
        horizon=params.horizon,
        num_samples=params.num_samples,
        dt=dt,
        noise_sigma=params.noise_sigma * torch.eye(2),
        temperature=params.temperature,
        control_cost_weight=params.control_cost_weight,
        seed=seed,
        cost_normalization="std",
        keep_rollouts=min(512, params.num_samples),
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
        params={**asdict(params), "num_seeds": num_seeds, "seed": seed, "dt": dt, "steps": steps},
    )


def reach_avoid(
    *,
    num_seeds: int = 10,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
    **params: Any,
) -> Scenario:
    """Build scenario A for ``num_seeds`` seeds; ``params``: fields of
    :class:`ReachAvoidParams` (e.g. ``num_samples=1000``)."""
    return ENTRY.make(num_seeds=num_seeds, seed=seed, device=device, dtype=dtype, **params)


ENTRY = register(
    ScenarioEntry(
        name="reach-avoid",
        build=build,
        params=ReachAvoidParams,
        description="Scenario A: timed reach-avoid with MPPI on a single integrator.",
        search_space=(
            Dimension("num_samples", "int", 256, 10_000, log=True),
            Dimension("horizon", "int", 20, 60),
            Dimension("temperature", "float", 1e-3, 1.0, log=True),
            Dimension("noise_sigma", "float", 0.5, 16.0, log=True),
            Dimension("control_cost_weight", "float", 1e-3, 1.0, log=True),
        ),
        columns=(
            Column("spec met [95% CI]", "spec_satisfied"),
            Column("collisions [95% CI]", "collision"),
            Column("min clearance [m]", "min_h", "min", "{:.3f}"),
        ),
        options={"samples": "num_samples", "horizon": "horizon"},
        units={"min_h": "m (clearance |p - o| - r_o)", "seconds": "s"},
        num_seeds=10,
        demo={"num_seeds": 4, "num_samples": 10_000, "horizon": 50},
        env=EnvEntry(
            id="torchcbf/ReachAvoid-v0",
            entry_point="torchcbf.envs.reach_avoid:ReachAvoidEnv",
            vector_entry_point="torchcbf.envs.reach_avoid:ReachAvoidVectorEnv",
            max_episode_steps=100,
        ),
    )
)
