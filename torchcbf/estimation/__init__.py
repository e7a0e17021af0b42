"""Sensors and Kalman-type estimators derived from a ControlAffine model, batched.

Protocol (what the closed-loop simulator calls; every estimator follows it)::

    state = estimator.init(x0_hat, P0)        # x0_hat [B, n], P0 [n, n] or [B, n, n]
    for k in range(steps):
        state = estimator.predict(state, u, dt)    # u [B, m] applied over dt
        y = sensor.measure(x_true, generator)      # y [B, p], noise from a torch.Generator
        state = estimator.update(state, y)
        u = controller(state.mean)                 # state.mean [B, n]

``estimator.step(state, u, dt, y)`` does ``predict`` then ``update``. States are NamedTuples
with ``mean [..., n]``, ``cov [..., n, n]`` and a per-row ``status [...]``
(:class:`EstimatorStatus` bits; numerical trouble never raises and never leaves a NaN: the row
keeps its previous estimate and is flagged). A :class:`Perfect` sensor with the
:class:`PassThrough` estimator (``mean = y``) is perfect state feedback.

Filters: :class:`EKF`, :class:`UKF`, :class:`HybridEKFUKF` (covariance intersection of the
two). Jacobians come from autograd; prediction is exact on linear systems (exponential
integrator for the mean, Van Loan for the covariance), see :class:`EKF`. Process noise ``Q``
is the continuous-time intensity (default: ``sigma sigma^T`` of the dynamics' diffusion).
"""

from torchcbf.estimation.base import Estimator, EstimatorState, EstimatorStatus, PassThrough
from torchcbf.estimation.ekf import EKF
from torchcbf.estimation.hybrid import HybridEKFUKF, HybridState
from torchcbf.estimation.sensors import (
    FunctionSensor,
    GaussianSensor,
    Perfect,
    RangeBearing,
    Sensor,
    wrap_angle,
)
from torchcbf.estimation.ukf import UKF

__all__ = [
    "EKF",
    "UKF",
    "Estimator",
    "EstimatorState",
    "EstimatorStatus",
    "FunctionSensor",
    "GaussianSensor",
    "HybridEKFUKF",
    "HybridState",
    "PassThrough",
    "Perfect",
    "RangeBearing",
    "Sensor",
    "wrap_angle",
]
