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
from typing import Any

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_finite

_EXACT = "_exact_constants"


def _own_dict(module: nn.Module, key: str) -> dict[str, Any]:
    """The dict ``module`` keeps under ``key`` in its ``__dict__`` (made on first use; not
    an attribute nn.Module tracks, so it is copied and pickled with the module)."""
    values = module.__dict__.get(key)
    if values is None:
        values = {}
        object.__setattr__(module, key, values)
    return values


def _exact_values(module: nn.Module) -> dict[str, Tensor]:
    return _own_dict(module, _EXACT)


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
    ``fn`` to its remembered exact value too; return the new tensor. A constant that
    requires grad is kept and ``name`` derived from it (:func:`derive`)."""
    derived = _derived(module).get(name)
    if derived is not None:  # reshaped before: apply fn after the earlier derivation
        _derived(module)[name] = (derived[0], _Then(derived[1], fn))
        return getattr(module, name)
    current = getattr(module, name)
    if isinstance(current, Tensor) and current.requires_grad:
        module._parameters.pop(name, None)
        module._buffers.pop(name, None)
        return derive(module, name, current, fn)
    setattr(module, name, fn(current))
    exact = _exact_values(module)
    if name in exact:
        exact[name] = fn(exact[name])
    return getattr(module, name)


_DERIVED = "_derived_constants"


def _derived(module: nn.Module) -> dict[str, tuple[str, Callable[[Tensor], Tensor]]]:
    return _own_dict(module, _DERIVED)


class DerivedConstants(nn.Module):
    """Mixin answering the constants :func:`derive` keeps as a function of their source."""

    def __getattr__(self, name: str) -> Any:
        # nn.Module's lookup written out (parameters, buffers, submodules), then the derived
        # constants: a module's own tensors cost no more than on a plain module
        own = self.__dict__
        for table in ("_parameters", "_buffers", "_modules"):
            values = own.get(table)
            if values is not None and name in values:
                return values[name]
        entry = (own.get(_DERIVED) or {}).get(name)
        if entry is not None:
            return entry[1](getattr(self, entry[0]))
        raise AttributeError(f"'{type(self).__name__}' object has no attribute '{name}'")


def derive_from(module: nn.Module, name: str, source: str, fn: Callable[[Tensor], Tensor]) -> None:
    """Make the constant ``name`` be ``fn`` of the constant ``source`` at every read (a
    Cholesky factor of a covariance that trains); ``module`` is a :class:`DerivedConstants`."""
    if not isinstance(module, DerivedConstants):
        raise TypeError(f"{type(module).__name__} cannot derive {name} from {source}")
    module._buffers.pop(name, None)
    _derived(module)[name] = (source, fn)


class _Then:
    """``second(first(t))``: two derivations in a row (picklable, unlike a lambda)."""

    def __init__(self, first: Callable[[Tensor], Tensor], second: Callable[[Tensor], Tensor]):
        self.first, self.second = first, second

    def __call__(self, t: Tensor) -> Tensor:
        return self.second(self.first(t))


def derive(
    module: nn.Module,
    name: str,
    value: object,
    fn: Callable[[object], Tensor | None],
    *,
    shape: Callable[[Tensor], Tensor] | None = None,
    exact: bool = False,
) -> Tensor | None:
    """Register the constant ``name = fn(value)`` (a checked cast, an expand, a diagonal
    matrix of a vector) and return it.

    A ``value`` that requires grad (an ``nn.Parameter``, a tensor with a graph) and that
    ``fn`` changes is kept as given as ``name + "_source"`` (a parameter stays one: the
    module trains it), and ``name`` is ``shape`` of it at every read (``fn`` where not
    given; ``shape`` makes what ``fn`` makes without its checks, which run once, here: a
    read then costs a cast or two and no host synchronisation): an optimiser step or an
    edit is seen, and each call has a graph of its own (``module`` is then a
    :class:`DerivedConstants`). One that ``fn`` leaves as it is, is registered as given (a
    parameter as a parameter). Anything else is stored as ``fn(value)``, a buffer
    (``exact``: Python numbers remembered, :func:`remember`)."""
    out = fn(value)
    module._buffers.pop(name, None)
    if isinstance(value, Tensor) and value.requires_grad:
        if out is value:
            return store(module, name, value)
        if not isinstance(module, DerivedConstants):
            raise TypeError(f"{type(module).__name__} cannot derive {name} from a tensor")
        store(module, name + "_source", value)
        _derived(module)[name] = (name + "_source", fn if shape is None else shape)
        return out
    if out is None or not exact:
        module.register_buffer(name, out)
        return out
    return remember(module, name, out, dtype=out.dtype)
