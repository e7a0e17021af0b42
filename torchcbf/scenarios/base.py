"""A ready closed-loop experiment: everything :func:`torchcbf.sim.simulate` needs, plus what
its metrics and figures read."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchcbf.dynamics.base import ControlAffine
from torchcbf.sim import Goal, Trajectory, metrics, simulate


@dataclass
class Scenario:
    """One experiment over a batch of seeds.

    ``barriers`` are the true obstacles (metrics and plots); ``goals`` the goal regions;
    ``spec`` a specification whose robustness decides success (optional); ``params`` every
    parameter the builder used (recorded with the results); ``extra_metrics(trajectory)``
    per-seed metrics of the scenario's own, added to the standard ones.
    """

    name: str
    dynamics: ControlAffine
    x0: Tensor
    steps: int
    dt: float
    seeds: Tensor
    planner: Any | None = None
    nominal: Callable[..., Tensor] | None = None
    safety_filter: Any | None = None
    integrator: str = "rk4"
    planner_every: int = 1
    barriers: Sequence[Callable[[Tensor], Tensor]] = ()
    goals: Sequence[Any] = ()
    metric_goals: Sequence[Goal] = ()
    spec: Any | None = None
    status_names: dict[int, str] = field(default_factory=dict)
    snapshot_steps: Sequence[int] = ()
    params: dict[str, Any] = field(default_factory=dict)
    extra_metrics: Callable[[Trajectory], dict[str, Tensor]] | None = None

    def run(self, progress: bool = True) -> tuple[Trajectory, dict[str, Tensor]]:
        """Simulate every seed in one batch; returns the trajectory and per-seed metrics."""
        traj = simulate(
            self.dynamics,
            self.x0,
            self.steps,
            self.dt,
            planner=self.planner,
            nominal=self.nominal,
            safety_filter=self.safety_filter,
            integrator=self.integrator,
            seed=self.seeds,
            progress=progress,
            progress_label=self.name,
            planner_every=self.planner_every,
            snapshot_steps=self.snapshot_steps,
        )
        with torch.no_grad():
            per_seed = metrics(
                traj,
                barriers=list(self.barriers) or None,
                goals=self.metric_goals,
                spec=self.spec,
                status_names=self.status_names,
            )
            if self.extra_metrics is not None:
                per_seed.update(self.extra_metrics(traj))
        return traj, per_seed
