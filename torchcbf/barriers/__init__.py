"""Barrier and Lyapunov functions as modules, with batched autograd Lie derivatives.

A barrier ``h(x[, t])`` is safe where ``h >= 0``; ``barrier.lie(x, dynamics, t)`` returns
:class:`LieTerms` ``(h, lfh, lgh, dhdt, hess_trace, dhdx)`` for a whole batch in one call.
Multi-output barriers (``h [..., k]``: batched shapes, :class:`BarrierStack`) give every
barrier's terms at once. :func:`rectify` turns a barrier of relative degree ``r > 1`` into
a relative-degree-one barrier (HOCBF or exponential CBF).
"""

from torchcbf.barriers.base import Barrier
from torchcbf.barriers.compose import BarrierStack, Intersection, Scaled, Transformed, Union
from torchcbf.barriers.lie import (
    AnalyticDerivatives,
    LieFunction,
    LieTerms,
    Quadric,
    lie_derivatives,
)
from torchcbf.barriers.lyapunov import Lyapunov, QuadraticLyapunov
from torchcbf.barriers.neural import NeuralBarrier
from torchcbf.barriers.rectify import (
    ExponentialBarrier,
    HighOrderBarrier,
    LieDerivative,
    coefficients_from_poles,
    find_relative_degree,
    rectify,
)
from torchcbf.barriers.shapes import Ball, Box, Ellipse, HalfSpace, MovingBall
from torchcbf.barriers.workspace import (
    EndEffectorBoxBarrier,
    JointLimitBarrier,
    JointVelocityBarrier,
    LinkBoxBarrier,
    LinkSphereBarrier,
    PointBarrier,
    box_signed_distance,
)

__all__ = [
    "EndEffectorBoxBarrier",
    "JointLimitBarrier",
    "JointVelocityBarrier",
    "LinkBoxBarrier",
    "LinkSphereBarrier",
    "PointBarrier",
    "box_signed_distance",
    "AnalyticDerivatives",
    "Ball",
    "Barrier",
    "BarrierStack",
    "Box",
    "Ellipse",
    "ExponentialBarrier",
    "HalfSpace",
    "HighOrderBarrier",
    "Intersection",
    "LieDerivative",
    "LieFunction",
    "LieTerms",
    "Lyapunov",
    "MovingBall",
    "NeuralBarrier",
    "QuadraticLyapunov",
    "Quadric",
    "Scaled",
    "Transformed",
    "Union",
    "coefficients_from_poles",
    "find_relative_degree",
    "lie_derivatives",
    "rectify",
]
