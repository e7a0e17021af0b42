"""A ready closed-loop experiment: a :class:`~torchcbf.sim.ClosedLoop` with its initial
states, its length and seeds, and what its metrics and figures read."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchcbf.sim import ClosedLoop, Goal, Trajectory, metrics


@dataclass(kw_only=True)
class Scenario(ClosedLoop):
    """One experiment over a batch of seeds: the closed loop (``dynamics``, ``planner``,
    ``nominal``, ``safety_filter``, ``integrator``, ``planner_every``, ... of
    :class:`~torchcbf.sim.ClosedLoop`) run from ``x0 [B, n]`` for ``steps`` steps of ``dt``.

    ``barriers`` are the true obstacles (metrics and plots); ``goals`` the goal regions (for
    the figures); ``metric_goals`` the goals the metrics time; ``spec`` a specification
    whose robustness decides success (optional); ``params`` every parameter the builder used
    (recorded with the results); ``extra_metrics(trajectory)`` per-seed metrics of the
    scenario's own, added to the standard ones.
    """

    name: str
    x0: Tensor
    steps: int
    dt: float
    seeds: Tensor
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
        traj = self.simulate(
            self.x0,
            self.steps,
            self.dt,
            seed=self.seeds,
            progress=progress,
            progress_label=self.name,
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
