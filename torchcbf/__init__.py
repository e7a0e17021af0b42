"""torchcbf: batched, differentiable safe planning and control in PyTorch.

The public names of the subpackages are re-exported here; figures (:mod:`torchcbf.viz`),
scenarios (:mod:`torchcbf.scenarios`) and training helpers (:mod:`torchcbf.learning`) are
imported from their own modules.
"""

from torchcbf._info import info
from torchcbf._version import __version__
from torchcbf.barriers import (
    Ball,
    Barrier,
    BarrierStack,
    Box,
    Ellipse,
    HalfSpace,
    Intersection,
    LieTerms,
    Lyapunov,
    MovingBall,
    NeuralBarrier,
    QuadraticLyapunov,
    Union,
    rectify,
)
from torchcbf.dynamics import (
    AccelUnicycle,
    Bicycle,
    ControlAffine,
    DoubleIntegrator,
    FixedWing,
    Manipulator,
    Quadrotor,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)
from torchcbf.estimation import EKF, UKF, GaussianSensor, HybridEKFUKF, Perfect
from torchcbf.filters import FilterOutput, FilterStatus, SafetyFilter, Slack
from torchcbf.integrators import step
from torchcbf.mppi import MPPI, Always, And, Avoid, Eventually, MPPIOutput, Or, Reach
from torchcbf.qp import QPSolution, Status, solve_qp
from torchcbf.sim import Trajectory, metrics, simulate, summarize

__all__ = [
    "__version__",
    "EKF",
    "MPPI",
    "UKF",
    "AccelUnicycle",
    "Always",
    "And",
    "Avoid",
    "Ball",
    "Barrier",
    "BarrierStack",
    "Bicycle",
    "Box",
    "ControlAffine",
    "DoubleIntegrator",
    "Ellipse",
    "Eventually",
    "FilterOutput",
    "FilterStatus",
    "FixedWing",
    "GaussianSensor",
    "HalfSpace",
    "HybridEKFUKF",
    "Intersection",
    "LieTerms",
    "Lyapunov",
    "MPPIOutput",
    "Manipulator",
    "MovingBall",
    "NeuralBarrier",
    "Or",
    "Perfect",
    "QPSolution",
    "QuadraticLyapunov",
    "Quadrotor",
    "Reach",
    "SafetyFilter",
    "SingleIntegrator",
    "Slack",
    "Status",
    "Trajectory",
    "Unicycle",
    "Union",
    "VanDerPol",
    "info",
    "metrics",
    "rectify",
    "simulate",
    "solve_qp",
    "step",
    "summarize",
]
