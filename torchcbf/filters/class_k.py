"""Extended class-K functions ``alpha(h)`` for CBF conditions (and CLF decay rates ``c(V)``).

Each is an ``nn.Module`` mapping values ``h [..., k]`` to ``alpha(h) [..., k]``, elementwise.
Gains are a scalar or one per output ``[k]`` (broadcast against the last axis). A learnable
gain is stored as an ``nn.Parameter`` in log form, so it stays positive while training.
:func:`as_class_k` turns the user-facing specifications (a number, a sequence or tensor of
gains, a callable, a module) into a module.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import TracksShadows, as_tensor
from torchcbf._constants import ExactConstants, remember

ClassKSpec = float | Sequence[float] | Tensor | Callable[[Tensor], Tensor] | nn.Module


def _gain(name: str, gain: float | Sequence[float] | Tensor) -> Tensor:
    """The gain as a tensor; one that requires grad keeps its graph (no silent cut)."""
    value = as_tensor(name, gain)
    value = value if value.requires_grad else value.detach().clone()
    if value.dim() > 1:
        raise ValueError(f"{name} must be a scalar or a vector [k], got shape {tuple(value.shape)}")
    check = value.detach()
    if check.numel() == 0 or not bool(torch.isfinite(check).all()) or bool((check <= 0).any()):
        raise ValueError(f"{name} must be finite and positive, got {value.tolist()}")
    return value


class _GainClassK(TracksShadows, ExactConstants):
    """A class-K function ``gain * phi(h)`` with a positive gain (fixed or learnable; a gain
    given as Python numbers stays exact under ``.double()``)."""

    def __init__(self, gain: float | Sequence[float] | Tensor = 1.0, learnable: bool = False):
        super().__init__()
        value = _gain("gain", gain)
        self.learnable = bool(learnable)
        if learnable and isinstance(gain, Tensor):
            self.log_gain = nn.Parameter(value.detach().log())
        elif learnable:  # log of the Python numbers, exact under .double()
            exact = as_tensor("gain", gain, dtype=torch.float64).log()
            remember(self, "log_gain", exact, learnable=True)
        elif isinstance(gain, Tensor):
            self.register_buffer("_gain", value)
        else:
            remember(self, "_gain", as_tensor("gain", gain, dtype=torch.float64))

    @property
    def gain(self) -> Tensor:
        """The positive gain, ``[]`` or ``[k]``."""
        return self.log_gain.exp() if self.learnable else self._gain

    def _phi(self, h: Tensor) -> Tensor:
        raise NotImplementedError

    def forward(self, h: Tensor) -> Tensor:
        """``h [..., k] -> alpha(h) [..., k]``."""
        return self.gain.to(h) * self._phi(h)

    def extra_repr(self) -> str:
        return f"gain={self.gain.detach().tolist()}, learnable={self.learnable}"


class LinearClassK(_GainClassK):
    """``alpha(h) = gain * h`` (gain ``> 0``, scalar or ``[k]``; ``learnable`` optional)."""

    def _phi(self, h: Tensor) -> Tensor:
        return h


class CubicClassK(_GainClassK):
    """``alpha(h) = gain * h^3``."""

    def _phi(self, h: Tensor) -> Tensor:
        return h**3


class PowerClassK(_GainClassK):
    """``alpha(h) = gain * sign(h) |h|^power`` (``power > 0``; extended class-K). Its
    derivative at ``h = 0`` is ``gain`` for ``power = 1``, 0 above, infinite below."""

    def __init__(
        self,
        gain: float | Sequence[float] | Tensor = 1.0,
        power: float = 1.0,
        learnable: bool = False,
    ) -> None:
        super().__init__(gain, learnable)
        if not isinstance(power, (int, float)) or not power > 0 or not math.isfinite(power):
            raise ValueError(f"power must be a finite positive number, got {power!r}")
        self.power = float(power)

    def _phi(self, h: Tensor) -> Tensor:
        p = self.power
        if p == 1.0:
            return h  # its derivative 1 at h = 0, where sign(h) |h| gives 0
        if p > 1.0:  # h |h|^(p-1), with the derivative 0 at h = 0 (no 0 * inf there)
            zero = h == 0
            return torch.where(zero, 0.0, h * torch.where(zero, 1.0, h.abs()) ** (p - 1.0))
        return torch.sign(h) * h.abs() ** p  # p < 1: the derivative at h = 0 is infinite

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, power={self.power}"


class _Callable(nn.Module):
    """Wrap a plain function ``h -> alpha(h)`` as a module."""

    def __init__(self, fn: Callable[[Tensor], Tensor]) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, h: Tensor) -> Tensor:
        return self.fn(h)


def as_class_k(spec: ClassKSpec, name: str = "alpha") -> nn.Module:
    """A class-K module from a specification.

    Args:
        spec: a positive number (linear gain), a sequence or tensor of positive gains (one
            per output, linear), an ``nn.Module`` (used as is, e.g. :class:`LinearClassK`
            with ``learnable=True``) or any callable ``h [..., k] -> [..., k]``.
        name: the argument name used in error messages.
    """
    if isinstance(spec, nn.Module):
        return spec
    if isinstance(spec, bool):
        raise TypeError(f"{name} must be a number, gains, a callable or a module, got a bool")
    if isinstance(spec, (int, float, Tensor)) or (
        isinstance(spec, Sequence) and all(isinstance(v, (int, float)) for v in spec)
    ):
        try:
            checked = _gain(name, spec)  # errors name the argument
            return LinearClassK(checked if isinstance(spec, Tensor) else spec)
        except TypeError as err:
            raise TypeError(f"{name}: {err}") from None
    if callable(spec):
        return _Callable(spec)
    raise TypeError(
        f"{name} must be a number, a sequence/tensor of gains, a callable or an nn.Module, "
        f"got {type(spec).__name__}"
    )
