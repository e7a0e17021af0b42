"""Constants of modules: stored so that gradients are never cut silently and Python numbers
stay exact in float64.

The rules every module built from numbers or tensors follows (:func:`store`):

- an ``nn.Parameter`` is registered as given (the module trains it);
- ``learnable=True`` registers a fresh ``nn.Parameter`` holding the value;
- a tensor that requires grad is kept as given, not detached: gradients flow back to it,
  as they would through a ``torch.nn.functional`` call (the module is then a function of that
  tensor; make it an ``nn.Parameter`` for the module to own it);
- any other tensor is copied into a buffer;
- Python numbers and sequences become a buffer in the default dtype, and their exact float64
  value is remembered: when the module is cast (``.double()``, ``.to(dtype)``), a constant
  still equal to its Python value is re-derived from that value, so a float64 module sees
  ``0.1`` and not ``float32(0.1)``. A constant changed since construction (trained, loaded,
  edited) is cast as usual.

Modules using :func:`store` or :func:`remember` derive from :class:`ExactConstants`. Models
store theirs as float64 buffers instead (``store(..., dtype=torch.float64)``, through
:func:`torchcbf.dynamics.base.register_constant`) and cast them to the input's dtype on use;
a model cast to float32 and back keeps the float32 rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_finite

_EXACT = "_exact_constants"


def _exact_values(module: nn.Module) -> dict[str, Tensor]:
    values = module.__dict__.get(_EXACT)
    if values is None:
        values = {}
        object.__setattr__(module, _EXACT, values)
    return values


class ExactConstants(nn.Module):
    """Mixin re-deriving remembered float64 constants when the module changes dtype."""

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> nn.Module:
        exact = self.__dict__.get(_EXACT) or {}
        untouched: dict[str, torch.dtype] = {}
        for name, value in exact.items():
            current = self._parameters.get(name, self._buffers.get(name))
            if current is None or current.device.type == "meta":
                continue
            ref = value.to(device=current.device, dtype=current.dtype)
            if current.shape == ref.shape and torch.equal(current.detach(), ref):
                untouched[name] = current.dtype
        out = super()._apply(fn, recurse)
        for name, old_dtype in untouched.items():
            current = self._parameters.get(name, self._buffers.get(name))
            if current is None or current.dtype == old_dtype or not current.is_floating_point():
                continue
            if current.device.type == "meta":
                continue
            value = exact[name].to(device=current.device, dtype=current.dtype)
            if isinstance(current, nn.Parameter):
                with torch.no_grad():
                    current.data = value
            else:
                self._buffers[name] = value
        return out


def remember(
    module: nn.Module,
    name: str,
    exact: Tensor,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | None = None,
    learnable: bool = False,
) -> Tensor:
    """Register the buffer (``learnable``: the parameter) ``name`` holding ``exact``
    (float64, from Python numbers) in ``dtype`` (default: the default dtype) on ``device``,
    and remember ``exact`` for :class:`ExactConstants`; return the tensor."""
    exact = exact.detach().to(torch.float64)
    value = exact.to(device=device, dtype=dtype or torch.get_default_dtype())
    if learnable:
        module.register_parameter(name, nn.Parameter(value))
    else:
        module.register_buffer(name, value)
    _exact_values(module)[name] = exact
    return getattr(module, name)


def store(
    module: nn.Module,
    name: str,
    value: object,
    *,
    learnable: bool = False,
    allow_inf: bool = False,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Register ``value`` on ``module`` as ``name`` following the module docstring's rules;
    return the stored tensor. ``dtype``: store numbers and tensors in it (default: numbers
    in the default dtype, tensors as given; a parameter, given or ``learnable``, is not
    cast). NaN (and ``inf`` unless ``allow_inf``) raises
    ``ValueError`` naming ``name``."""
    if isinstance(value, nn.Parameter):
        check_finite(name, value, allow_inf=allow_inf)
        module.register_parameter(name, value)
        return value
    if isinstance(value, Tensor):
        t = as_tensor(name, value, dtype=dtype)
        check_finite(name, t, allow_inf=allow_inf)
        if learnable:
            module.register_parameter(name, nn.Parameter(t.detach().clone()))
        elif t.requires_grad:
            module.register_buffer(name, t)
        else:
            module.register_buffer(name, t.detach().clone())
        return getattr(module, name)
    exact = as_tensor(name, value, dtype=torch.float64)
    check_finite(name, exact, allow_inf=allow_inf)
    # a parameter is not cast (see above): the default dtype, as nn.Parameter(number) would
    return remember(module, name, exact, dtype=None if learnable else dtype, learnable=learnable)


def reshape(module: nn.Module, name: str, fn: Callable[[Tensor], Tensor]) -> Tensor:
    """Replace the constant ``name`` by ``fn(constant)`` (an expand, an unsqueeze), applying
    ``fn`` to its remembered exact value too; return the new tensor."""
    setattr(module, name, fn(getattr(module, name)))
    exact = _exact_values(module)
    if name in exact:
        exact[name] = fn(exact[name])
    return getattr(module, name)
