"""Batched closed-loop simulation, its record and its metrics."""

from torchcbf.sim.metrics import Goal, metrics, summarize, wilson_interval
from torchcbf.sim.simulate import simulate
from torchcbf.sim.trajectory import Trajectory

__all__ = ["Goal", "Trajectory", "metrics", "simulate", "summarize", "wilson_interval"]
