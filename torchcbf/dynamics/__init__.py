"""Control-affine dynamics: the :class:`ControlAffine` base and standard models."""

from torchcbf.dynamics._ik import IKResult
from torchcbf.dynamics.base import ControlAffine, DriftDerivatives, NativeModel
from torchcbf.dynamics.manipulator import (
    JointSpaceController,
    Manipulator,
    ResolvedRateController,
    asset_path,
)
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
    "DriftDerivatives",
    "FixedWing",
    "IKResult",
    "JointSpaceController",
    "Manipulator",
    "NativeModel",
    "Quadrotor",
    "ResolvedRateController",
    "SingleIntegrator",
    "Unicycle",
    "VanDerPol",
    "asset_path",
]
