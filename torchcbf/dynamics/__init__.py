"""Control-affine dynamics: the :class:`ControlAffine` base and standard models."""

from torchcbf.dynamics.base import ControlAffine
from torchcbf.dynamics.models import (
    AccelUnicycle,
    Bicycle,
    DoubleIntegrator,
    FixedWing,
    Quadrotor,
    SingleIntegrator,
    Unicycle,
    VanDerPol,
)

__all__ = [
    "AccelUnicycle",
    "Bicycle",
    "ControlAffine",
    "DoubleIntegrator",
    "FixedWing",
    "Quadrotor",
    "SingleIntegrator",
    "Unicycle",
    "VanDerPol",
]
