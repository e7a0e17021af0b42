"""Matplotlib figures and animations of closed-loop runs and MPPI rollouts."""

from torchcbf.viz.compare import animate_methods, barrier_traces, plot_barrier_bands, plot_methods
from torchcbf.viz.figures import (
    animate,
    axis_labels,
    draw_goals,
    draw_unsafe_set,
    mark_minimum,
    plot_barrier_values,
    plot_rollouts,
    plot_trajectories,
    weight_ranks,
)

__all__ = [
    "animate",
    "animate_methods",
    "axis_labels",
    "barrier_traces",
    "draw_goals",
    "draw_unsafe_set",
    "mark_minimum",
    "plot_barrier_bands",
    "plot_barrier_values",
    "plot_methods",
    "plot_rollouts",
    "plot_trajectories",
    "weight_ranks",
]
