"""Continuous-discrete unscented Kalman filter derived from a ControlAffine model."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcbf._autograd import needs_graph, outside_inference_mode
from torchcbf._checks import check_number
from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation._linalg import discretize, jacobian, robust_cholesky, symmetrize
from torchcbf.estimation.base import EstimatorState, EstimatorStatus, RowGuard, _KalmanFilter
from torchcbf.estimation.sensors import Sensor


class UKF(_KalmanFilter):
    """Unscented Kalman filter with scaled sigma points, batched over scenarios.

    ``2n + 1`` sigma points ``m, m +- sqrt(n + lam) L_i`` (``L`` a robust Cholesky factor of
    ``P``, ``lam = alpha^2 (n + kappa) - n``), weights ``Wm_0 = lam / (n + lam)``,
    ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``, ``W_i = 1 / (2 (n + lam))``.

    Prediction (per substep of length ``h``): each sigma point goes through the same
    step map as the :class:`EKF` mean, the exponential-Euler step linearized at that point
    (exact for linear dynamics); ``P = sum Wc (Y - m)(Y - m)^T + Qd`` with the Van Loan
    ``Qd`` of ``Q_c`` under the Jacobian at the mean. On a linear system this is the exact
    Kalman filter. Update: sigma points through ``sensor.expected``; means and deviations of
    the measurements use ``sensor.residual`` (so bearings are averaged on the circle);
    ``K = P_xy S^-1`` and ``P - K S K^T`` in Joseph form, ``(I - K H) P (I - K H)^T +
    K (R + D) K^T`` with the statistically linearised sensor ``H = P_xy^T P^-1`` (``C``
    itself for a linear sensor) and ``D = sum Wc E E^T`` of the sigma points' linearisation
    errors ``E = dY - dX H^T``: the same covariance, positive semidefinite by construction,
    where the difference loses the variance to rounding when the measurement is far more
    precise than the prior (a negative variance with ``P = 1e10``, ``R = 1e-6`` in float64).
    A negative centre weight (``beta + 1 - alpha^2 < 0``) can make ``D`` indefinite: it is
    then clamped to its positive semidefinite part, a larger covariance than the difference
    (which may be indefinite), and the row is flagged ``REGULARIZED``.

    The default ``alpha = 1`` (``lam = kappa``) keeps the weights of order ``1/n``: small
    ``alpha`` (e.g. 1e-3) gives weights of order ``1/alpha^2`` whose cancellation costs about
    ``-2 log10(alpha)`` digits, too many in float32.

    Args:
        dynamics, sensor, Q, R, substeps: as for :class:`EKF`.
        alpha, beta, kappa: sigma-point spread, prior-kurtosis weight and secondary scaling
            (``n + kappa`` must be positive).
    """

    def __init__(
        self,
        dynamics: ControlAffine,
        sensor: Sensor,
        Q: Tensor | float | None = None,
        R: Tensor | float | None = None,
        *,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        substeps: int = 1,
    ) -> None:
        super().__init__(dynamics, sensor, Q, R, substeps=substeps)
        n = self.state_dim
        alpha = check_number("alpha", alpha, low=0.0, strict=True)
        beta = check_number("beta", beta)
        kappa = check_number("kappa", kappa)
        if not n + kappa > 0:
            raise ValueError(f"n + kappa must be positive, got n={n}, kappa={kappa}")
        #: the sigma-point parameters, read at each step (a value set later is used)
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)

    def _scale(self) -> float:
        """``n + lam = alpha^2 (n + kappa)`` of the parameters as they are now."""
        c = float(self.alpha) ** 2 * (self.state_dim + float(self.kappa))
        if not c > 0:
            raise ValueError(
                f"alpha^2 (n + kappa) must be positive, got alpha={self.alpha}, "
                f"kappa={self.kappa}, n={self.state_dim}"
            )
        return c

    def _center_weight(self) -> float:
        """The covariance weight of the centre sigma point, ``lam / (n + lam) + 1 - alpha^2 +
        beta``."""
        c = self._scale()
        return (c - self.state_dim) / c + 1.0 - float(self.alpha) ** 2 + float(self.beta)

    def _weights(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and covariance weights ``[2n+1]`` in the dtype/device of ``like`` (Python
        floats cast at use: no float32 rounding of a float64 filter's weights)."""
        c = self._scale()  # n + lam
        lam = c - self.state_dim
        kw = {"dtype": like.dtype, "device": like.device}
        # filled, not indexed: a Python number written into a device tensor waits for it
        rest = torch.full((2 * self.state_dim,), 0.5 / c, **kw)
        wm = torch.cat([torch.full((1,), lam / c, **kw), rest])
        wc = torch.cat([torch.full((1,), self._center_weight(), **kw), rest])
        return wm, wc

    def _sigma_points(self, m: Tensor, P: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Sigma points ``[B, 2n+1, n]``, their deviations from ``m`` and a regularized flag."""
        L, regularized = robust_cholesky(P)
        D = math.sqrt(self._scale()) * L.mT  # row i is column i of L
        dX = torch.cat([torch.zeros_like(m).unsqueeze(1), D, -D], dim=1)
        return m.unsqueeze(1) + dX, dX, regularized

    def _mean(self, Y: Tensor, Wm: Tensor, residual) -> tuple[Tensor, Tensor]:
        """Weighted mean of ``Y [B, 2n+1, k]`` taken relative to ``Y_0``, and deviations."""
        Y0 = Y[:, :1]
        ybar = Y0.squeeze(1) + (Wm[1:, None] * residual(Y[:, 1:], Y0)).sum(1)
        return ybar, residual(Y, ybar.unsqueeze(1))

    @outside_inference_mode
    def predict(self, state: EstimatorState, u: Tensor, dt: float) -> EstimatorState:
        """Propagate ``state`` (mean ``[..., n]``, cov ``[..., n, n]``) with ``u [..., m]``."""
        bs, m0, P0, u, dt, skip = self._flat_predict(state, u, dt)
        guard = RowGuard()
        m, P, u = guard.watch(m0), guard.watch(P0), guard.watch(u)
        B, n = m.shape
        Wm, Wc = self._weights(m)
        h = dt / self.substeps
        status = torch.zeros(B, dtype=torch.int64, device=m.device)
        u_rep = u.unsqueeze(1).expand(B, 2 * n + 1, u.shape[-1]).reshape(-1, u.shape[-1])
        for _ in range(self.substeps):
            X, _, regularized = self._sigma_points(m, P)
            status = status | torch.where(regularized, int(EstimatorStatus.REGULARIZED), 0)
            Xf = X.reshape(-1, n)
            graph = needs_graph(self.dynamics, Xf, u_rep)
            xdot, F = jacobian(lambda z: self.dynamics(z, u_rep), Xf, graph)
            xdot, F = guard.watch(xdot, 2 * n + 1), guard.watch(F, 2 * n + 1)
            _, dx, _ = discretize(F, h, xdot)
            Y = (Xf + dx).reshape(B, 2 * n + 1, n)
            F0 = F.reshape(B, 2 * n + 1, n, n)[:, 0]
            _, _, Qd = discretize(F0, h, None, self._Qc(m, guard))
            m, dY = self._mean(Y, Wm, torch.sub)
            P = symmetrize((dY * Wc[:, None]).mT @ dY + Qd)
        return self._finish(bs, m0, P0, m, P, status, guard, skip=skip)

    @outside_inference_mode
    def update(self, state: EstimatorState, y: Tensor) -> EstimatorState:
        """Correct ``state`` with ``y [..., p]`` (a non-finite ``y`` row is skipped and flagged)."""
        bs, m0, P0, status, y, skip = self._flat_update(state, y)
        guard = RowGuard()
        m, P, y = guard.watch(m0), guard.watch(P0), guard.watch(y)
        R = self._R(m, guard)
        Wm, Wc = self._weights(m)
        X, dX, reg_p = self._sigma_points(m, P)
        Yp = guard.watch(self.sensor.expected(X))
        y_pred, dY = self._mean(Yp, Wm, self.sensor.residual)
        WdY = dY * Wc[:, None]
        S = symmetrize(WdY.mT @ dY + R)
        Pxy = dX.mT @ WdY  # [B, n, p]
        L, reg_s = robust_cholesky(S)
        K = torch.cholesky_solve(Pxy.mT, L).mT  # Pxy S^-1
        mean = m + (K @ self.sensor.residual(y, y_pred).unsqueeze(-1)).squeeze(-1)
        # P - K S K' in Joseph form: with the statistically linearised sensor H = Pxy' P^-1
        # (the sensor's own matrix where it is linear) and the sigma points' linearisation
        # errors E, S = H P H' + R + D with D = sum Wc E E', so P - K S K' = A P A' +
        # K (R + D) K': a sum of positive semidefinite terms, where the difference cancels
        # to rounding, or below zero, when the measurement is far more precise than the prior
        Lp, _ = robust_cholesky(P)
        H = torch.cholesky_solve(Pxy, Lp).mT  # [B, p, n]
        E = dY - dX @ H.mT  # [B, 2n+1, p]
        D = symmetrize((E * Wc[:, None]).mT @ E)
        clamped = torch.zeros_like(reg_p)
        if self._center_weight() < 0:  # a negative weight: D may be indefinite
            vals, vecs = torch.linalg.eigh(D)
            # rounding is of the order of S's entries (D of a linear sensor is all rounding)
            tol = 64 * torch.finfo(D.dtype).eps * S.diagonal(dim1=-2, dim2=-1).abs().amax(-1)
            clamped = (vals.amin(-1) < -tol).detach()
            D = (vecs * vals.clamp_min(0.0).unsqueeze(-2)) @ vecs.mT
        A = torch.eye(m.shape[-1], dtype=m.dtype, device=m.device) - K @ H
        cov = A @ P @ A.mT + K @ (R + D) @ K.mT
        flags = torch.where(reg_p | reg_s | clamped, int(EstimatorStatus.REGULARIZED), 0)
        return self._finish(bs, m0, P0, mean, cov, status | flags, guard, skip=skip)
