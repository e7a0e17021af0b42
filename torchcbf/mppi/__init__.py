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
from torchcbf.mppi.defaults import MPPISettings, propose_settings
from torchcbf.mppi.history import History, HistoryBuffer
from torchcbf.mppi.interpolated import KMPPI, rbf_kernel
from torchcbf.mppi.planner import MPPI, MPPIOutput
from torchcbf.mppi.shield import ShieldMPPI
from torchcbf.mppi.smooth import SMPPI
from torchcbf.mppi.specs import Always, And, Avoid, Eventually, Or, Reach, Spec

__all__ = [
    "MPPISettings",
    "propose_settings",
    "KMPPI",
    "MPPI",
    "SMPPI",
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
    "rbf_kernel",
    "ShieldMPPI",
    "RolloutCost",
    "Spec",
    "StageCost",
    "SumCost",
]
