"""Sensor models ``y = h(x) + v``, ``v ~ N(0, R)``, as ``nn.Module``s.

Every sensor has
- ``expected(x) -> [..., p]``: the noise-free measurement ``h(x)`` (differentiable);
- ``measure(x, generator=None, *, noise=None) -> [..., p]``: a noisy measurement, the noise
  drawn from ``generator`` (never from the global random state) or given as a standard-normal
  ``noise [..., p]``; ``forward`` is ``measure``;
- ``residual(y, y_pred) -> [..., p]``: the innovation ``y - y_pred``, with the components
  listed in ``angle_index`` wrapped to ``[-pi, pi)`` (the filters always use it);
- buffers ``R [p, p]`` (``None`` for :class:`Perfect`) and ``R_sqrt`` (lower Cholesky factor);
  attributes ``output_dim`` (``p``, ``None`` when it equals the state size) and
  ``state_dim`` (``n`` when the sensor knows it, else ``None``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchcbf._checks import (
    as_tensor,
    broadcasts_to,
    check_finite,
    check_generator,
    check_last_dim,
    check_positive,
    check_same,
    check_spd,
    check_tensor,
)
from torchcbf._constants import (
    DerivedConstants,
    ExactConstants,
    derive,
    derive_from,
    remember,
    store,
)
from torchcbf.barriers._params import take
from torchcbf.estimation._linalg import wrap_angle

__all__ = ["FunctionSensor", "GaussianSensor", "Perfect", "RangeBearing", "Sensor", "wrap_angle"]


class Sensor(ExactConstants, DerivedConstants):
    """Base class: subclasses implement :meth:`expected` and call ``_set_noise``.

    Noise given as Python numbers is exact under ``.double()``; a tensor that requires grad
    keeps its gradient (see :mod:`torchcbf._constants`)."""

    output_dim: int | None
    state_dim: int | None

    def __init__(
        self,
        output_dim: int | None = None,
        state_dim: int | None = None,
        angle_index: Sequence[int] = (),
    ) -> None:
        super().__init__()
        self.output_dim = output_dim
        self.state_dim = state_dim
        self.angle_index = tuple(int(i) for i in angle_index)
        if output_dim is not None and any(i < 0 or i >= output_dim for i in self.angle_index):
            raise ValueError(
                f"angle_index={self.angle_index} is outside an output of size {output_dim}"
            )
        self.register_buffer("R", None)
        self.register_buffer("R_sqrt", None)
        mask = None
        if self.angle_index and output_dim is not None:
            mask = torch.zeros(output_dim, dtype=torch.bool)
            mask[list(self.angle_index)] = True
        self.register_buffer("angle_mask", mask)

    def _set_noise(
        self, value: object, fn: Callable[[object], Tensor], *, exact: bool = False
    ) -> None:
        """Register ``R = fn(value) [p, p]`` (``value``: the covariance, or the standard
        deviations it is made of) and its Cholesky factor ``R_sqrt``; ``exact``: ``value`` is
        Python numbers (``R`` stored in the default dtype, re-derived by ``.double()``). A
        ``value`` that requires grad is kept, and both are made from it at each read."""
        R = fn(value)
        p = R.shape[-1]
        if R.shape != (p, p) or (self.output_dim is not None and p != self.output_dim):
            raise ValueError(
                f"R must have shape [{self.output_dim}, {self.output_dim}], got {tuple(R.shape)}"
            )
        check_finite("R", R)
        check_spd("R", R)
        if isinstance(value, Tensor) and value.requires_grad:
            shape = functools.partial(_variances, p=p)  # std (a tensor R is kept as given)
            derive(self, "R", value, fn, shape=shape)
            derive_from(self, "R_sqrt", "R", torch.linalg.cholesky)
        elif exact:
            remember(self, "R", R)
            remember(self, "R_sqrt", torch.linalg.cholesky(R))
        else:
            self.R = R
            self.R_sqrt = torch.linalg.cholesky(R)

    def expected(self, x: Tensor) -> Tensor:
        """Noise-free measurement ``h(x)``: ``[..., n] -> [..., p]``."""
        raise NotImplementedError(f"{type(self).__name__} must define expected(x)")

    def _wrap(self, y: Tensor) -> Tensor:
        if self.angle_mask is None:
            return y
        # like C, R_sqrt and the landmarks, the mask follows the input's device
        return torch.where(self.angle_mask.to(y.device), wrap_angle(y), y)

    def residual(self, y: Tensor, y_pred: Tensor) -> Tensor:
        """Innovation ``y - y_pred`` ``[..., p]``, angle components wrapped to ``[-pi, pi)``."""
        return self._wrap(y - y_pred)

    def measure(
        self, x: Tensor, generator: torch.Generator | None = None, *, noise: Tensor | None = None
    ) -> Tensor:
        """Noisy measurement ``h(x) + R_sqrt z`` for ``x [..., n]``: returns ``[..., p]``.

        ``z ~ N(0, I_p)`` comes from ``generator`` or is given as ``noise [..., p]``; one of
        them is required (a sensor never draws from the global random state).
        """
        y = self.expected(x)
        if self.R_sqrt is None:
            return y
        p = y.shape[-1]
        if noise is None:
            if generator is None:
                raise ValueError(
                    f"{type(self).__name__}.measure needs generator= or noise= (torchcbf never "
                    "draws from the global random state); expected(x) is the noise-free output"
                )
            check_generator(generator, "x", y)
            noise = torch.randn(y.shape, generator=generator, device=y.device, dtype=y.dtype)
        else:
            check_last_dim("noise", noise, p)
            check_same("x", y, "noise", noise)
            if not broadcasts_to(noise.shape[:-1], y.shape[:-1]):
                raise ValueError(
                    f"noise [..., {p}] must broadcast to the batch of x {tuple(y.shape[:-1])}, "
                    f"got {tuple(noise.shape)}"
                )
        y = y + noise @ self.R_sqrt.to(y).mT
        return self._wrap(y)

    def forward(
        self, x: Tensor, generator: torch.Generator | None = None, *, noise: Tensor | None = None
    ) -> Tensor:
        """Same as :meth:`measure`."""
        return self.measure(x, generator, noise=noise)


def _from_numbers(value: object) -> bool:
    return value is not None and not isinstance(value, Tensor)


def _noise(std: object, R: object, p: int | None) -> tuple[object, Callable[[object], Tensor]]:
    """Exactly one of ``std`` (scalar or ``[p]``) and ``R`` (``[p, p]``), with the function
    that makes the covariance of it."""
    if (std is None) == (R is None):
        raise ValueError("give exactly one of std= (standard deviations) and R= (covariance)")
    if R is not None:
        return R, _covariance  # a tensor R is kept as it is
    return std, functools.partial(_covariance_of_std, p=p)


def _covariance(R: object) -> Tensor:
    """``R [p, p]`` as given (a tensor), or exact float64 of Python numbers."""
    R_t = _number_or_tensor("R", R)
    if R_t.dim() != 2:
        raise ValueError(f"R must be a matrix [p, p], got {tuple(R_t.shape)}")
    return R_t


def _covariance_of_std(std: object, p: int | None) -> Tensor:
    """``diag(std^2)`` of standard deviations given as a scalar (needs ``p``) or ``[p]``."""
    s = check_finite("std", _number_or_tensor("std", std))
    if s.dim() == 0 and p is None:
        raise ValueError("a scalar std needs the output size (output_dim/state_dim or C)")
    if s.dim() > 1 or (s.dim() == 1 and p is not None and s.shape[0] != p):
        raise ValueError(f"std must be a scalar or have shape [{p}], got {tuple(s.shape)}")
    if not bool((s.detach() > 0).all()):
        raise ValueError(f"std must be positive, got {s.detach().tolist()}")
    return _variances(s, p)


def _variances(std: Tensor, p: int | None) -> Tensor:
    """``diag(std^2)`` of standard deviations checked by :func:`_covariance_of_std` (a
    scalar repeated ``p`` times): what a sensor reads at each step from a ``std`` that
    trains."""
    s = std.expand(p) if std.dim() == 0 else std
    return torch.diag(s**2)


def _number_or_tensor(name: str, value: object) -> Tensor:
    """A tensor as given (floating), Python numbers as exact float64."""
    if isinstance(value, Tensor):
        return as_tensor(name, value)
    return as_tensor(name, value, dtype=torch.float64)


class Perfect(Sensor):
    """The exact state: ``y = x`` (no noise, ``R = None``). Pair it with
    :class:`~torchcbf.estimation.PassThrough` (or no estimator at all)."""

    def __init__(self) -> None:
        super().__init__()

    def expected(self, x: Tensor) -> Tensor:
        """``y = x``: ``[..., n] -> [..., n]``."""
        return check_tensor("x", x)


class GaussianSensor(Sensor):
    """Linear sensor ``y = C x + v``, ``v ~ N(0, R)``.

    Args:
        C: ``[p, n]`` (identity when ``None``: then the size comes from ``state_dim``, a
            vector ``std`` or ``R``).
        std: standard deviations, scalar or ``[p]`` (``R = diag(std^2)``); or
        R: covariance ``[p, p]``, symmetric positive definite.
        state_dim: ``n`` when ``C`` is ``None`` and the size is not implied by ``std``/``R``.
    """

    def __init__(
        self,
        C: Tensor | None = None,
        std: float | Sequence[float] | Tensor | None = None,
        *,
        R: Tensor | None = None,
        state_dim: int | None = None,
    ) -> None:
        if C is not None:
            C_t = check_finite("C", _number_or_tensor("C", C))
            if C_t.dim() != 2:
                raise ValueError(f"C must be a matrix [p, n], got {tuple(C_t.shape)}")
            if state_dim is not None and C_t.shape[1] != state_dim:
                raise ValueError(f"C must have {state_dim} columns, got {tuple(C_t.shape)}")
            p: int | None = C_t.shape[0]
        else:
            p = state_dim
            if p is None:
                ref = R if R is not None else std
                ref_t = None if ref is None else as_tensor("std" if R is None else "R", ref)
                if ref_t is not None and ref_t.dim() >= 1:
                    p = ref_t.shape[0]
            if p is None:
                raise ValueError("GaussianSensor without C needs state_dim=, a vector std or R")
            C_t = torch.eye(p, dtype=torch.float64)
        noise, covariance = _noise(std, R, p)
        covariance(noise)  # checked before the module is built
        super().__init__(output_dim=C_t.shape[0], state_dim=C_t.shape[1])
        if C is None or _from_numbers(C):
            remember(self, "C", C_t)
        else:
            store(self, "C", C_t)
        self._set_noise(noise, covariance, exact=_from_numbers(std) or _from_numbers(R))

    def expected(self, x: Tensor) -> Tensor:
        """``C x``: ``[..., n] -> [..., p]``."""
        check_last_dim("x", x, self.C.shape[1])
        if not x.is_floating_point():
            raise TypeError(f"x must be a floating-point tensor, got {x.dtype}")
        return x @ self.C.to(x).mT


class FunctionSensor(Sensor):
    """Nonlinear sensor ``y = fn(x) + v``, ``v ~ N(0, R)``, ``fn: [..., n] -> [..., p]``.

    ``fn`` must be written with torch operations (the EKF differentiates it with autograd,
    the UKF evaluates it at sigma points of shape ``[B, 2n+1, n]``). An ``nn.Module`` ``fn``
    is registered as a submodule.

    Args:
        fn: the measurement function.
        R: covariance ``[p, p]``; or ``std``: scalar (needs ``output_dim``) or ``[p]``.
        output_dim: ``p`` (checked against ``R``/``std`` when both are given).
        state_dim: ``n`` if known (checked by the filters).
        angle_index: output components that are angles (wrapped in ``residual``).
    """

    def __init__(
        self,
        fn: Callable[[Tensor], Tensor],
        R: Tensor | None = None,
        *,
        std: float | Sequence[float] | Tensor | None = None,
        output_dim: int | None = None,
        state_dim: int | None = None,
        angle_index: Sequence[int] = (),
    ) -> None:
        if not callable(fn):
            raise TypeError(f"fn must be callable, got {type(fn).__name__}")
        noise, covariance = _noise(std, R, output_dim)
        p = covariance(noise).shape[-1]
        if output_dim is not None and p != output_dim:
            raise ValueError(f"R must have shape [{output_dim}, {output_dim}], got {(p, p)}")
        super().__init__(output_dim=p, state_dim=state_dim, angle_index=angle_index)
        self.fn = fn
        self._set_noise(noise, covariance, exact=_from_numbers(std) or _from_numbers(R))

    def expected(self, x: Tensor) -> Tensor:
        """``fn(x)``: ``[..., n] -> [..., p]``, angle components wrapped."""
        check_tensor("x", x)
        if self.state_dim is not None:
            check_last_dim("x", x, self.state_dim)
        y = self.fn(x)
        if not isinstance(y, Tensor) or y.shape[-1:] != (self.output_dim,):
            got = tuple(y.shape) if isinstance(y, Tensor) else type(y).__name__
            raise ValueError(f"fn(x) must return [..., {self.output_dim}], got {got}")
        return self._wrap(y)


class RangeBearing(Sensor):
    """Range and bearing to ``L`` known landmarks: ``y = [r_1, b_1, ..., r_L, b_L]`` (``p = 2L``).

    ``r_i = |l_i - pos|``, ``b_i = atan2(l_i - pos) - heading`` wrapped to ``[-pi, pi)``
    (absolute bearing when ``heading_index`` is ``None``). Range has no derivative at a
    landmark: keep landmarks away from the robot.

    Args:
        landmarks: ``[L, 2]`` planar positions.
        std_range, std_bearing: noise standard deviations (metres, radians).
        position_index: the state components of the position (default ``(0, 1)``).
        heading_index: the heading component: 2 for ``Unicycle``/``Bicycle``, 3 for
            ``AccelUnicycle``; ``None`` for absolute bearings.
    """

    def __init__(
        self,
        landmarks: Tensor | Sequence[Sequence[float]],
        std_range: float,
        std_bearing: float,
        *,
        position_index: tuple[int, int] = (0, 1),
        heading_index: int | None = 2,
    ) -> None:
        lm = check_finite("landmarks", _number_or_tensor("landmarks", landmarks))
        if lm.dim() != 2 or lm.shape[1] != 2 or lm.shape[0] < 1:
            raise ValueError(f"landmarks must have shape [L, 2], got {tuple(lm.shape)}")
        check_positive("std_range", std_range)
        check_positive("std_bearing", std_bearing)
        L = lm.shape[0]
        super().__init__(output_dim=2 * L, angle_index=range(1, 2 * L, 2))
        if _from_numbers(landmarks):
            remember(self, "landmarks", lm)
        else:
            store(self, "landmarks", lm)
        self.position_index = tuple(int(i) for i in position_index)
        if len(self.position_index) != 2:
            raise ValueError(f"position_index must name 2 components, got {position_index}")
        self.heading_index = None if heading_index is None else int(heading_index)
        var = torch.tensor([std_range**2, std_bearing**2], dtype=torch.float64).repeat(L)
        self._set_noise(torch.diag(var), _covariance, exact=True)

    def expected(self, x: Tensor) -> Tensor:
        """``[r_1, b_1, ..., r_L, b_L]``: ``[..., n] -> [..., 2L]``."""
        check_tensor("x", x)
        need = max(
            self.position_index + ((self.heading_index,) if self.heading_index is not None else ())
        )
        if x.dim() == 0 or x.shape[-1] <= need:
            raise ValueError(f"x must have shape [..., n] with n > {need}, got {tuple(x.shape)}")
        pos = take(x, self.position_index)
        d = self.landmarks.to(x) - pos.unsqueeze(-2)  # [..., L, 2]
        rng = torch.linalg.vector_norm(d, dim=-1)
        bearing = torch.atan2(d[..., 1], d[..., 0])
        if self.heading_index is not None:
            bearing = bearing - x[..., self.heading_index].unsqueeze(-1)
        y = torch.stack([rng, wrap_angle(bearing)], dim=-1)
        return y.reshape(*y.shape[:-2], 2 * y.shape[-2])
