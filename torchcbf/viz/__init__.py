"""Matplotlib figures and animations of closed-loop runs and MPPI rollouts."""

from torchcbf.viz.figures import (
    animate,
    draw_goals,
    draw_unsafe_set,
    plot_barrier_values,
    plot_rollouts,
    plot_trajectories,
)

__all__ = [
    "animate",
    "draw_goals",
    "draw_unsafe_set",
    "plot_barrier_values",
    "plot_rollouts",
    "plot_trajectories",
]
