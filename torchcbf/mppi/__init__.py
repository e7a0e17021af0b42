"""MPPI planner, rollout costs and timed reach-avoid specifications."""

from torchcbf.mppi.costs import (
    BarrierCost,
    DiscreteBarrierCost,
    ObstacleCost,
    QuadraticGoal,
    RolloutCost,
    StageCost,
    SumCost,
)
from torchcbf.mppi.history import History, HistoryBuffer
from torchcbf.mppi.planner import MPPI, MPPIOutput
from torchcbf.mppi.shield import ShieldMPPI
from torchcbf.mppi.specs import Always, And, Avoid, Eventually, Or, Reach, Spec

__all__ = [
    "MPPI",
    "Always",
    "And",
    "Avoid",
    "BarrierCost",
    "DiscreteBarrierCost",
    "Eventually",
    "History",
    "HistoryBuffer",
    "MPPIOutput",
    "ObstacleCost",
    "Or",
    "QuadraticGoal",
    "Reach",
    "ShieldMPPI",
    "RolloutCost",
    "Spec",
    "StageCost",
    "SumCost",
]
