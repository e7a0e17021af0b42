"""Batched closed-loop simulation, its record and its metrics."""

from torchcbf.sim.metrics import Goal, metrics, summarize, wilson_interval
from torchcbf.sim.records import run_info, strict
from torchcbf.sim.simulate import simulate
from torchcbf.sim.trajectory import Trajectory

__all__ = [
    "Goal",
    "Trajectory",
    "metrics",
    "run_info",
    "simulate",
    "strict",
    "summarize",
    "wilson_interval",
]
