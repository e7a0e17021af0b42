"""Hybrid EKF-UKF: both filters run side by side; their estimates are fused by covariance
intersection."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import broadcast_shapes
from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation._linalg import robust_cholesky, symmetrize
from torchcbf.estimation.base import Estimator, EstimatorState, EstimatorStatus
from torchcbf.estimation.ekf import EKF
from torchcbf.estimation.sensors import Sensor
from torchcbf.estimation.ukf import UKF


class HybridState(NamedTuple):
    """State of :class:`HybridEKFUKF`: the fused ``mean [..., n]``, ``cov [..., n, n]``,
    ``status [...]`` (bits of both filters and of the fusion) and each filter's own state."""

    mean: Tensor
    cov: Tensor
    status: Tensor
    ekf: EstimatorState
    ukf: EstimatorState


class HybridEKFUKF(Estimator):
    """An :class:`EKF` and a :class:`UKF` on the same model and sensor, fused every call.

    Each filter keeps and propagates its own state (the fused estimate is never fed back).
    The fusion is covariance intersection: ``P^-1 = w P_e^-1 + (1 - w) P_u^-1``,
    ``m = m_u + w P P_e^-1 (m_e - m_u)``, with ``w`` in ``[0, 1]`` chosen on a fixed grid of
    ``ci_points`` values to minimise ``det P``. Covariance intersection stays consistent for
    any correlation between the two estimates, which here is strong (they share every
    measurement); the information sum ``(P_e^-1 + P_u^-1)^-1`` would assume them independent
    and be over-confident. (CBFkit blends the two means with a heuristic weight from the ratio
    of covariance norms and reports no fused covariance.) On a linear system both filters
    are the exact Kalman filter and so is the fusion.

    Args:
        dynamics, sensor, Q, R, substeps: as for :class:`EKF`.
        alpha, beta, kappa: the UKF's sigma-point parameters.
        ci_points: size of the grid for the fusion weight ``w`` (``>= 2``).
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
        ci_points: int = 33,
    ) -> None:
        super().__init__()
        if isinstance(ci_points, bool) or not isinstance(ci_points, int) or ci_points < 2:
            raise ValueError(f"ci_points must be an integer >= 2, got {ci_points!r}")
        self.ekf = EKF(dynamics, sensor, Q, R, substeps=substeps)
        self.ukf = UKF(
            dynamics, sensor, Q, R, alpha=alpha, beta=beta, kappa=kappa, substeps=substeps
        )
        self.state_dim = self.ekf.state_dim
        self.ci_points = ci_points

    def init(self, x0: Tensor, P0: Tensor | None = None) -> HybridState:
        """Both filters start from ``x0 [..., n]``, ``P0 [..., n, n]``."""
        e = self.ekf.init(x0, P0)
        u = self.ukf.init(x0, P0)
        return HybridState(e.mean, e.cov, e.status, e, u)

    def _check(self, state: object) -> HybridState:
        if not isinstance(state, HybridState):
            raise TypeError(f"state must be a HybridState from init(), got {type(state).__name__}")
        return state

    def predict(self, state: HybridState, u: Tensor, dt: float) -> HybridState:
        """Predict both filters with ``u [..., m]`` over ``dt`` and fuse."""
        state = self._check(state)
        return self._fuse(self.ekf.predict(state.ekf, u, dt), self.ukf.predict(state.ukf, u, dt))

    def update(self, state: HybridState, y: Tensor) -> HybridState:
        """Update both filters with ``y [..., p]`` and fuse."""
        state = self._check(state)
        return self._fuse(self.ekf.update(state.ekf, y), self.ukf.update(state.ukf, y))

    def _fuse(self, e: EstimatorState, u: EstimatorState) -> HybridState:
        bs = broadcast_shapes(e.mean.shape[:-1], u.mean.shape[:-1])
        n = e.mean.shape[-1]
        me, mu = e.mean.expand(*bs, n).reshape(-1, n), u.mean.expand(*bs, n).reshape(-1, n)
        Pe = e.cov.expand(*bs, n, n).reshape(-1, n, n)
        Pu = u.cov.expand(*bs, n, n).reshape(-1, n, n)
        Le, reg_e = robust_cholesky(Pe)
        Lu, reg_u = robust_cholesky(Pu)
        Ie, Iu = torch.cholesky_inverse(Le), torch.cholesky_inverse(Lu)
        w = torch.linspace(0.0, 1.0, self.ci_points, dtype=me.dtype, device=me.device)
        info = w[:, None, None] * Ie.unsqueeze(1) + (1 - w[:, None, None]) * Iu.unsqueeze(1)
        Lw, bad = torch.linalg.cholesky_ex(symmetrize(info))  # [B, K, n, n]
        logdet = Lw.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        logdet = torch.where(bad == 0, logdet, torch.full_like(logdet, -torch.inf))
        best = logdet.argmax(-1)  # a row whose every candidate failed falls back to w = 0
        wb = w[best]
        info_b = torch.gather(info, 1, best[:, None, None, None].expand(-1, 1, n, n)).squeeze(1)
        Lb, reg_b = robust_cholesky(info_b)
        P = torch.cholesky_inverse(Lb)
        innov = (Ie @ (me - mu).unsqueeze(-1)).squeeze(-1)
        mean = mu + wb[:, None] * (P @ innov.unsqueeze(-1)).squeeze(-1)
        P = symmetrize(P)
        flags = torch.where(reg_e | reg_u | reg_b, int(EstimatorStatus.REGULARIZED), 0)
        finite = torch.isfinite(mean).all(-1) & torch.isfinite(P).flatten(1).all(-1)
        mean = torch.where(finite[:, None], mean, mu)
        P = torch.where(finite[:, None, None], P, Pu)
        flags = flags | torch.where(finite, 0, int(EstimatorStatus.NON_FINITE))
        status = e.status.expand(bs).reshape(-1) | u.status.expand(bs).reshape(-1) | flags
        return HybridState(mean.reshape(*bs, n), P.reshape(*bs, n, n), status.reshape(bs), e, u)
