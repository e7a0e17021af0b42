"""Continuous-discrete extended Kalman filter derived from a ControlAffine model."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcbf._autograd import needs_graph, outside_inference_mode
from torchcbf.estimation._linalg import discretize, jacobian, robust_cholesky, symmetrize
from torchcbf.estimation.base import EstimatorState, EstimatorStatus, RowGuard, _KalmanFilter


class EKF(_KalmanFilter):
    """Extended Kalman filter: continuous-time model, discrete measurements, batched.

    Prediction over ``dt`` (in ``substeps`` equal pieces of length ``h``), each piece
    linearized at the current mean with ``F = d(f + g u)/dx`` from autograd:

    - mean: exponential Euler ``m <- m + phi1(F h) h (f(m) + g(m) u)``, ``phi1(z) = (e^z-1)/z``
      (exact for linear dynamics with the control held, second order otherwise);
    - covariance: ``P <- Phi P Phi^T + Qd`` with ``Phi = exp(F h)`` and the Van Loan integral
      ``Qd = int_0^h exp(F s) Q_c exp(F s)^T ds``, i.e. the exact solution of
      ``Pdot = F P + P F^T + Q_c`` for the frozen ``F``.

    Both come from one matrix exponential per piece, so on a linear system the EKF is the
    exact Kalman filter of the sampled linear SDE. Update: ``H = dh/dx`` by autograd at the
    prior mean, innovation ``sensor.residual(y, h(m))`` (angles wrapped), Joseph form
    ``P = (I - K H) P (I - K H)^T + K R K^T``, symmetrised.

    Args:
        dynamics: the model (its Jacobians come from autograd; no hand-written derivatives).
        sensor: a noisy :class:`~torchcbf.estimation.Sensor` (not ``Perfect``).
        Q: continuous process-noise intensity ``[n, n]`` (scalar or diagonal ``[n]`` allowed),
            symmetric positive definite; ``None``: ``sigma sigma^T`` of the dynamics.
        R: measurement covariance ``[p, p]``; ``None``: the sensor's ``R``.
        substeps: pieces per ``predict`` (re-linearization points).
    """

    @outside_inference_mode
    def predict(self, state: EstimatorState, u: Tensor, dt: float) -> EstimatorState:
        """Propagate ``state`` (mean ``[..., n]``, cov ``[..., n, n]``) with ``u [..., m]``."""
        bs, m0, P0, u, dt, skip = self._flat_predict(state, u, dt)
        guard = RowGuard()
        m, P, u = guard.watch(m0), guard.watch(P0), guard.watch(u)
        h = dt / self.substeps
        graph = needs_graph(self.dynamics, m, u)
        for _ in range(self.substeps):
            xdot, F = jacobian(lambda z: self.dynamics(z, u), m, graph)
            xdot, F = guard.watch(xdot), guard.watch(F)
            Phi, dx, Qd = discretize(F, h, xdot, self._Qc(m, guard))
            m = m + dx
            P = symmetrize(Phi @ P @ Phi.mT + Qd)
        status = torch.zeros(m.shape[0], dtype=torch.int64, device=m.device)
        return self._finish(bs, m0, P0, m, P, status, guard, skip=skip)

    @outside_inference_mode
    def update(self, state: EstimatorState, y: Tensor) -> EstimatorState:
        """Correct ``state`` with ``y [..., p]`` (a non-finite ``y`` row is skipped and flagged)."""
        bs, m0, P0, status, y, skip = self._flat_update(state, y)
        guard = RowGuard()
        m, P, y = guard.watch(m0), guard.watch(P0), guard.watch(y)
        graph = needs_graph(self.sensor, m)
        y_pred, H = jacobian(self.sensor.expected, m, graph)
        y_pred, H = guard.watch(y_pred), guard.watch(H)
        R = self._R(m, guard)
        S = symmetrize(H @ P @ H.mT + R)
        L, regularized = robust_cholesky(S)
        K = torch.cholesky_solve(H @ P, L).mT  # P H^T S^-1, [B, n, p]
        mean = m + (K @ self.sensor.residual(y, y_pred).unsqueeze(-1)).squeeze(-1)
        A = torch.eye(m.shape[-1], dtype=m.dtype, device=m.device) - K @ H
        cov = A @ P @ A.mT + K @ R @ K.mT
        status = status | torch.where(regularized, int(EstimatorStatus.REGULARIZED), 0)
        return self._finish(bs, m0, P0, mean, cov, status, guard, skip=skip)
