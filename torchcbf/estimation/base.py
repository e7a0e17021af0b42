"""The estimator protocol, its state, :class:`PassThrough` and the shared Kalman-filter base."""

from __future__ import annotations

import functools
from enum import IntEnum
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchcbf._checks import (
    as_matrix,
    as_tensor,
    broadcast_shapes,
    broadcasts_to,
    check_batch_match,
    check_finite,
    check_last_dim,
    check_positive,
    check_same,
    check_spd,
    check_tensor,
    matrix_shape,
    per_row,
    rows_finite,
)
from torchcbf._constants import DerivedConstants, ExactConstants, derive, remember
from torchcbf.dynamics.base import ControlAffine
from torchcbf.estimation._linalg import symmetrize
from torchcbf.estimation.sensors import Perfect, Sensor


class EstimatorStatus(IntEnum):
    """Per-row status bits of an :class:`EstimatorState` (a row may carry several, OR-ed).

    ``REGULARIZED``: a covariance (``P`` or the innovation covariance ``S``) was not
    numerically positive definite and a jitter or diagonal fallback was used, or the
    covariance the step returns is not (rounding of a prior far wider than the measurement
    in float32, say: the next step factors it with a jitter).
    ``NON_FINITE``: the step produced a non-finite value in that row (or its measurement
    was non-finite); the row kept its previous mean and covariance.
    """

    OK = 0
    REGULARIZED = 1
    NON_FINITE = 2


class EstimatorState(NamedTuple):
    """State of an estimator for a batch of scenarios.

    Attributes:
        mean: ``[..., n]`` state estimate.
        cov: ``[..., n, n]`` covariance (symmetric positive definite for the Kalman filters).
        status: ``[...]`` int64, :class:`EstimatorStatus` bits of the last ``predict`` and the
            ``update`` that followed it (``predict`` clears the bits, ``update`` adds).
    """

    mean: Tensor
    cov: Tensor
    status: Tensor


class Estimator(nn.Module):
    """Protocol of every estimator (what the simulator calls)::

        state = estimator.init(x0_hat, P0)           # once
        state = estimator.predict(state, u, dt)      # each step, u applied over dt
        y = sensor.measure(x_true, generator)        # the sensor the estimator was built with
        state = estimator.update(state, y)
        controller(state.mean)

    ``step(state, u, dt, y)`` is ``update(predict(state, u, dt), y)``. States are
    NamedTuples with at least ``mean [..., n]``, ``cov [..., n, n]`` and ``status [...]``.
    """

    state_dim: int | None

    def init(self, x0: Tensor, P0: Tensor | None = None) -> EstimatorState:
        """Initial state from the prior mean ``x0 [..., n]`` and covariance ``P0``: ``[n, n]``
        or ``[..., n, n]`` whose batch broadcasts to that of ``x0``, in ``x0``'s dtype and
        device. The Kalman filters need ``P0`` (symmetric positive definite); ``PassThrough``
        takes ``None`` as zeros."""
        raise NotImplementedError(f"{type(self).__name__} must define init")

    def predict(self, state: EstimatorState, u: Tensor, dt: float) -> EstimatorState:
        """Propagate over ``dt`` with the control ``u [..., m]`` held constant."""
        raise NotImplementedError(f"{type(self).__name__} must define predict")

    def update(self, state: EstimatorState, y: Tensor) -> EstimatorState:
        """Correct with the measurement ``y [..., p]``."""
        raise NotImplementedError(f"{type(self).__name__} must define update")

    def step(self, state: EstimatorState, u: Tensor, dt: float, y: Tensor) -> EstimatorState:
        """``update(predict(state, u, dt), y)``."""
        return self.update(self.predict(state, u, dt), y)


class PassThrough(Estimator):
    """The identity estimator for a :class:`~torchcbf.estimation.Perfect` sensor: the mean is
    the last measurement, the covariance zero, ``predict`` changes nothing.

    Args:
        state_dim: ``n`` if known (then measurements are checked against it).
    """

    def __init__(self, state_dim: int | None = None) -> None:
        super().__init__()
        self.state_dim = state_dim

    def init(self, x0: Tensor, P0: Tensor | None = None) -> EstimatorState:
        """``mean = x0 [..., n]``, ``cov = P0`` (``[n, n]`` or ``[..., n, n]``, broadcast to
        the batch of ``x0``; zeros when ``None``), status OK."""
        x0 = check_finite("x0", _check_vector("x0", x0, self.state_dim))
        n = x0.shape[-1]
        cov = x0.new_zeros(*x0.shape, n) if P0 is None else _check_cov("P0", P0, x0, spd=False)
        return EstimatorState(x0, cov, _zero_status(x0))

    def predict(self, state: EstimatorState, u: Tensor, dt: float) -> EstimatorState:
        """Returns ``state`` unchanged (after checking ``dt``)."""
        _check_state(state, self.state_dim)
        check_positive("dt", dt)
        return state

    def update(self, state: EstimatorState, y: Tensor) -> EstimatorState:
        """``mean = y [..., n]`` (broadcast with the state's batch), zero covariance; a row
        of ``y`` that is not finite keeps the previous estimate, flagged ``NON_FINITE``."""
        mean, cov, _ = _check_state(state, self.state_dim)
        n = mean.shape[-1]
        check_last_dim("y", y, n)
        check_same("state.mean", mean, "y", y)
        check_batch_match("state.mean", mean, "y", y)
        bs = broadcast_shapes(mean.shape[:-1], y.shape[:-1])
        y = y.expand(*bs, n)
        ok = torch.isfinite(y.detach()).all(-1)
        new_mean = torch.where(ok.unsqueeze(-1), y, mean.expand(*bs, n))
        new_cov = torch.where(ok[..., None, None], 0.0, cov.expand(*bs, n, n))
        status = torch.where(ok, 0, int(EstimatorStatus.NON_FINITE))
        return EstimatorState(new_mean, new_cov, status)


# -- helpers shared by the Kalman filters ----------------------------------------------------


def _zero_status(mean: Tensor) -> Tensor:
    return torch.zeros(mean.shape[:-1], dtype=torch.int64, device=mean.device)


def _check_vector(name: str, x: object, n: int | None) -> Tensor:
    x = check_tensor(name, x)
    if x.dim() == 0 or (n is not None and x.shape[-1] != n):
        raise ValueError(
            f"{name} must have shape [..., {n if n is not None else 'n'}], got {tuple(x.shape)}"
        )
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {x.dtype}")
    return x


def _check_cov(name: str, P: object, mean: Tensor, *, spd: bool = True) -> Tensor:
    """Check ``P [..., n, n]`` against ``mean [..., n]`` and broadcast it to the mean's batch."""
    P = check_tensor(name, P)
    n = mean.shape[-1]
    if P.dim() < 2 or P.shape[-2:] != (n, n):
        raise ValueError(f"{name} must have shape [..., {n}, {n}], got {tuple(P.shape)}")
    if not broadcasts_to(P.shape[:-2], mean.shape[:-1]):
        raise ValueError(
            f"the batch of {name} {tuple(P.shape)} must broadcast to that of x0 {tuple(mean.shape)}"
        )
    check_same("x0", mean, name, P)
    if spd:
        check_spd(name, P)
    else:
        check_finite(name, P)
    return P.expand(*mean.shape, n)


def _check_state(state: object, n: int | None) -> tuple[Tensor, Tensor, Tensor]:
    if not (isinstance(state, tuple) and hasattr(state, "mean") and hasattr(state, "cov")):
        raise TypeError(f"state must be an EstimatorState from init(), got {type(state).__name__}")
    mean = _check_vector("state.mean", state.mean, n)
    k = mean.shape[-1]
    cov = check_tensor("state.cov", state.cov)
    if cov.shape != mean.shape + (k,):
        raise ValueError(
            f"state.cov must have shape {tuple(mean.shape) + (k,)}, got {tuple(cov.shape)}"
        )
    status = state.status
    if not isinstance(status, Tensor) or status.shape != mean.shape[:-1]:
        raise ValueError(f"state.status must have shape {tuple(mean.shape[:-1])}")
    return mean, cov, status


def _noise_spec(module: nn.Module, buffer: str, name: str, value: object, n: int) -> Tensor:
    """Register as ``buffer`` the covariance argument ``name``: a scalar (``v I``), a vector
    (diagonal) or ``[n, n]`` (symmetric positive definite), exact under ``.double()`` when
    given as numbers; a tensor keeps its dtype, and one that requires grad is kept and made
    the matrix at each read (:func:`~torchcbf._constants.derive`: a parameter trains)."""
    if isinstance(value, Tensor):
        check = functools.partial(as_matrix, name, size=n)
        out = derive(module, buffer, value, check, shape=functools.partial(matrix_shape, size=n))
        assert out is not None
        return out
    return remember(module, buffer, as_matrix(name, value, n, dtype=torch.float64))


class RowGuard:
    """Keeps a step's rejected rows out of the gradient of everything the rows share.

    A row the step rejects (not finite, :meth:`_KalmanFilter._finish`) keeps its previous
    estimate, so the step's own result on it gets no gradient; yet the backward of the
    step's operations on that row (an exponential that overflowed, a product with an
    infinity) still forms ``0 * inf = NaN``, which a shared ``Q`` or ``R`` sums over the
    rows. The tensors :meth:`watch` returns (the step's inputs, and what the model, the
    sensor and the noise give per row) have those rows' gradient set to zero in the
    backward pass, once :attr:`bad` is known. Inputs that are not finite never reach the
    model (a stand-in takes their place); a value that overflows inside the model itself
    can still reach the model's own parameters through its backward."""

    def __init__(self) -> None:
        self.bad: Tensor | None = None

    def watch(self, t: Tensor, repeat: int = 1) -> Tensor:
        """``t [B * repeat, ...]`` (each row's ``repeat`` entries together) as an alias whose
        gradient skips the bad rows; the tensor itself is left alone (the rejected rows'
        previous estimate takes its gradient through it)."""
        if not t.requires_grad:
            return t
        alias = t.view_as(t)
        alias.register_hook(functools.partial(self._zero, repeat=repeat))
        return alias

    def _zero(self, g: Tensor | None, repeat: int) -> Tensor | None:
        if g is None or self.bad is None:  # the step is still running (a Jacobian's backward)
            return g
        bad = self.bad.repeat_interleave(repeat) if repeat > 1 else self.bad
        return torch.where(per_row(bad, g), 0.0, g)


def _output_size(sensor: Sensor, R: object) -> int:
    """The measurement size ``p`` an ``R`` override must have: the sensor's, or the size of
    the sensor's own ``R``, or that of the override itself (a scalar needs one of the
    others)."""
    if sensor.output_dim is not None:
        return sensor.output_dim
    if sensor.R is not None:
        return sensor.R.shape[-1]
    R_t = as_tensor("R", R)
    if R_t.dim() == 0:
        raise ValueError(
            f"a scalar R needs the measurement size: {type(sensor).__name__} declares no "
            "output_dim and no R of its own; give R as a vector [p] or a matrix [p, p]"
        )
    return R_t.shape[-1]


class _KalmanFilter(ExactConstants, DerivedConstants, Estimator):
    """Shared construction, validation and batching of the Kalman-type filters.

    Process noise: ``Q`` is the continuous-time intensity ``Q_c [n, n]`` of the white noise
    in ``dx = (f + g u) dt + dW_Q``; it must be symmetric positive definite (given as a scalar
    ``q I``, a diagonal ``[n]`` or ``[n, n]``). With ``Q=None`` the dynamics' diffusion is used,
    ``Q_c = sigma(x) sigma(x)^T`` evaluated at the mean (positive semidefinite is fine there);
    a model without diffusion then needs an explicit ``Q``.
    """

    def __init__(
        self,
        dynamics: ControlAffine,
        sensor: Sensor,
        Q: Tensor | float | None = None,
        R: Tensor | float | None = None,
        *,
        substeps: int = 1,
    ) -> None:
        super().__init__()
        if not isinstance(dynamics, ControlAffine):
            raise TypeError(
                f"dynamics must be a ControlAffine module, got {type(dynamics).__name__}"
            )
        if not isinstance(sensor, Sensor):
            raise TypeError(f"sensor must be a Sensor module, got {type(sensor).__name__}")
        n = dynamics.state_dim
        if isinstance(sensor, Perfect):
            raise ValueError(
                "a Perfect sensor needs no Kalman filter: use PassThrough (or no estimator)"
            )
        if sensor.state_dim is not None and sensor.state_dim != n:
            raise ValueError(f"sensor expects states of size {sensor.state_dim}, dynamics has {n}")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
        self.dynamics = dynamics
        self.sensor = sensor
        self.state_dim = n
        self.substeps = substeps
        if Q is None and not dynamics.has_diffusion:
            raise ValueError(
                f"Q is required: {type(dynamics).__name__} has no diffusion sigma to derive it from"
            )
        self.register_buffer("Q", None)
        if Q is not None:
            _noise_spec(self, "Q", "Q", Q, n)
        self.register_buffer("R_override", None)
        if R is None:
            if sensor.R is None:
                raise ValueError(f"R is required: {type(sensor).__name__} has no noise covariance")
        else:
            _noise_spec(self, "R_override", "R", R, _output_size(sensor, R))

    # -- pieces used by the subclasses ------------------------------------------------------
    def _R(self, like: Tensor, guard: RowGuard) -> Tensor:
        """The measurement covariance ``[B, p, p]`` for the rows of ``like [B, n]``."""
        R = self.R_override if self.R_override is not None else self.sensor.R
        return guard.watch(R.to(like).expand(like.shape[0], -1, -1))

    def _Qc(self, m: Tensor, guard: RowGuard) -> Tensor:
        """Continuous process-noise intensity at the mean ``m [B, n]``: ``[B, n, n]``."""
        if self.Q is not None:
            return guard.watch(self.Q.to(m).expand(m.shape[0], -1, -1))
        s = self.dynamics.sigma(m)
        return guard.watch(s @ s.mT)

    def init(self, x0: Tensor, P0: Tensor | None = None) -> EstimatorState:
        """Prior mean ``x0 [..., n]`` and covariance ``P0`` (required): ``[n, n]`` or
        ``[..., n, n]`` whose batch broadcasts to that of ``x0``, symmetric positive definite,
        in ``x0``'s dtype and device.

        Returns an :class:`EstimatorState` with the batch of ``x0``.
        """
        x0 = check_finite("x0", _check_vector("x0", x0, self.state_dim))
        if x0.dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"x0 must be float32 or float64 (the factorisations need them), got {x0.dtype}"
            )
        if P0 is None:
            raise ValueError(f"{type(self).__name__}.init needs the prior covariance P0")
        P = _check_cov("P0", P0, x0)
        return EstimatorState(x0, P, _zero_status(x0))

    def _flat_predict(self, state: EstimatorState, u: Tensor, dt: float):
        mean, cov, status = _check_state(state, self.state_dim)
        dt = check_positive("dt", dt)
        check_last_dim("u", u, self.dynamics.control_dim)
        check_same("state.mean", mean, "u", u)
        check_batch_match("state.mean", mean, "u", u)
        bs = broadcast_shapes(mean.shape[:-1], u.shape[:-1])
        n, m = self.state_dim, self.dynamics.control_dim
        u = u.expand(*bs, m).reshape(-1, m)
        # a control that is not finite is answered by a finite stand-in, then by the
        # previous estimate (_finish's skip): the model never sees it, so its parameters'
        # gradient never meets it
        u_ok = rows_finite(u, 1, u.shape[0])
        return (
            bs,
            mean.expand(*bs, n).reshape(-1, n),
            cov.expand(*bs, n, n).reshape(-1, n, n),
            torch.where(u_ok[:, None], u, 0.0),
            dt,
            ~u_ok,
        )

    def _flat_update(self, state: EstimatorState, y: Tensor):
        mean, cov, status = _check_state(state, self.state_dim)
        R = self.R_override if self.R_override is not None else self.sensor.R
        p = R.shape[-1]
        check_last_dim("y", y, p)
        check_same("state.mean", mean, "y", y)
        check_batch_match("state.mean", mean, "y", y)
        bs = broadcast_shapes(mean.shape[:-1], y.shape[:-1])
        n = self.state_dim
        y = y.expand(*bs, p).reshape(-1, p)
        # a non-finite row is answered by a finite stand-in, then by the previous estimate
        # (_finish's skip): its NaN never enters a product whose gradient reaches the batch
        y_ok = rows_finite(y, 1, y.shape[0])
        return (
            bs,
            mean.expand(*bs, n).reshape(-1, n),
            cov.expand(*bs, n, n).reshape(-1, n, n),
            status.expand(bs).reshape(-1),
            torch.where(y_ok[:, None], y, 0.0),
            ~y_ok,
        )

    @staticmethod
    def _finish(
        bs: torch.Size,
        prev_mean: Tensor,
        prev_cov: Tensor,
        mean: Tensor,
        cov: Tensor,
        status: Tensor,
        guard: RowGuard,
        skip: Tensor | None = None,
    ) -> EstimatorState:
        """Symmetrise, flag a covariance that is not numerically positive definite, reject
        non-finite rows and the rows ``skip [B]`` marks (keep the previous estimate, flagged
        ``NON_FINITE``, and out of the gradient through ``guard``) and reshape."""
        cov = symmetrize(cov)
        finite = torch.isfinite(mean.detach()).all(-1) & torch.isfinite(cov.detach()).flatten(
            1
        ).all(-1)
        if skip is not None:
            finite = finite & ~skip
        guard.bad = ~finite
        not_pd = finite & (torch.linalg.cholesky_ex(cov.detach())[1] != 0)
        status = status | torch.where(not_pd, int(EstimatorStatus.REGULARIZED), 0)
        mean = torch.where(finite[:, None], mean, prev_mean)
        cov = torch.where(finite[:, None, None], cov, prev_cov)
        status = status | torch.where(finite, 0, int(EstimatorStatus.NON_FINITE))
        n = mean.shape[-1]
        return EstimatorState(mean.reshape(*bs, n), cov.reshape(*bs, n, n), status.reshape(bs))
