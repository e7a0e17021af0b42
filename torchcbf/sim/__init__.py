"""Batched closed-loop simulation, its record and its metrics."""

from torchcbf.sim.loop import ClosedLoop, Filter, Nominal, Planner
from torchcbf.sim.metrics import Goal, metrics, summarize, wilson_interval
from torchcbf.sim.records import run_info, strict
from torchcbf.sim.simulate import simulate
from torchcbf.sim.trajectory import Trajectory

__all__ = [
    "ClosedLoop",
    "Filter",
    "Goal",
    "Nominal",
    "Planner",
    "Trajectory",
    "metrics",
    "run_info",
    "simulate",
    "strict",
    "summarize",
    "wilson_interval",
]
