"""Autograd for the library's own derivatives: whether a computation must record a graph
(the test behind the fast paths that carry no gradient and run only built-in code: the
planner's C kernel, the estimators' Jacobians; code that calls user functions, as the
safety filter's real-time path, asks its own results instead, since a user closure may hold
a tensor that requires grad), and recording whatever the caller's grad or inference mode."""

from __future__ import annotations

import contextlib
import functools
import itertools
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

import torch
from torch import Tensor, nn
from torch.autograd import forward_ad

_F = TypeVar("_F", bound=Callable[..., Any])


def forward_mode_active() -> bool:
    """Whether a forward-mode AD level is open (``torch.autograd.forward_ad.dual_level``):
    a tangent may then ride on any tensor, one captured by a user's closure too."""
    return forward_ad._current_level >= 0


def refuse_transforms(
    where: str, tensors: Iterable[Tensor | None], *, module: nn.Module | None = None
) -> None:
    """Raise ``NotImplementedError`` inside a ``torch.func`` transform (``vmap``,
    ``jacrev``, ...), or where a tensor of ``tensors`` (or, under a forward-mode level, of
    ``module``'s parameters and buffers) carries a forward-mode tangent
    (``torch.autograd.forward_ad``) or is a batched gradient (``is_grads_batched``):
    ``where`` has plain reverse-mode derivatives only, and a tangent would otherwise be
    dropped without a word (``None``: no derivative)."""
    functorch = torch._C._functorch
    if functorch.maybe_current_level() is not None:
        raise _batched(where)
    dual = forward_mode_active()
    if module is not None and dual:
        tensors = itertools.chain(tensors, module.parameters(), module.buffers())
    for t in tensors:
        if t is None:
            continue
        # is_grads_batched and vectorised jacobians batch a backward by torch's legacy vmap
        if functorch.is_functorch_wrapped_tensor(t) or functorch.is_legacy_batchedtensor(t):
            raise _batched(where)
        if dual and forward_ad.unpack_dual(t).tangent is not None:
            raise NotImplementedError(
                f"{where} has reverse-mode derivatives only: forward-mode AD "
                "(torch.autograd.forward_ad) would drop the tangent; use torch.autograd.grad "
                "or torch.autograd.functional.jacobian"
            )


def _batched(where: str) -> NotImplementedError:
    return NotImplementedError(
        f"{where} does not run under torch.func transforms or batched gradients (vmap, "
        "jacrev, jacfwd, grad, is_grads_batched=True, jacobian(vectorize=True)): batch the "
        "problems along the leading dimensions instead, and take derivatives with "
        "torch.autograd (reverse mode, one gradient at a time)"
    )


@contextlib.contextmanager
def recording() -> Iterator[None]:
    """Grad mode on, and inference mode off where it is on (autograd records nothing
    there): for the library's own derivatives, whatever mode the caller is in."""
    if torch.is_inference_mode_enabled():
        with torch.inference_mode(False), torch.enable_grad():
            yield
    else:
        with torch.enable_grad():
            yield


def recordable(value: Any) -> Any:
    """``value``, with an inference tensor (made under ``torch.inference_mode``, which
    autograd cannot save) replaced by a normal copy; tuples (named ones too) entry by
    entry."""
    if isinstance(value, Tensor):
        return value.clone() if value.is_inference() else value
    if isinstance(value, tuple):
        items = [recordable(v) for v in value]
        return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
    return value


def _holds_inference(value: Any) -> bool:
    if isinstance(value, Tensor):
        return value.is_inference()
    return isinstance(value, tuple) and any(_holds_inference(v) for v in value)


def outside_inference_mode(method: _F) -> _F:
    """Run ``method`` (whose results come from autograd derivatives) outside inference
    mode: under ``torch.inference_mode`` as under ``torch.no_grad``, and with inference
    tensors among its arguments replaced by normal copies."""

    @functools.wraps(method)
    def run(*args: Any, **kwargs: Any) -> Any:
        inference = torch.is_inference_mode_enabled()
        if not inference and not _holds_inference((*args, *kwargs.values())):
            return method(*args, **kwargs)
        args, kwargs = recordable(args), {k: recordable(v) for k, v in kwargs.items()}
        if not inference:
            return method(*args, **kwargs)
        with torch.inference_mode(False), torch.no_grad():
            return method(*args, **kwargs)

    return run  # type: ignore[return-value]


def needs_graph(
    module: nn.Module, *tensors: Tensor | None, module_grad: bool | None = None
) -> bool:
    """Whether an output computed from ``module`` and ``tensors`` can carry a gradient: grad
    mode is on and one of the tensors, or a parameter or buffer of ``module`` (a buffer may
    be a tensor given with ``requires_grad``), requires grad. ``module_grad``: whether one
    of those parameters and buffers requires grad, where the caller knows (no walk)."""
    if not torch.is_grad_enabled():
        return False
    if any(t is not None and t.requires_grad for t in tensors):
        return True
    if module_grad is not None:
        return module_grad
    for sub in module.modules():
        for group in (sub._parameters, sub._buffers):
            for t in group.values():
                if t is not None and t.requires_grad:
                    return True
    return False


def reaches_other_leaf(out: Tensor, x: Tensor) -> bool:
    """Whether ``out``'s graph reaches a tensor that requires grad other than ``x`` (a
    tensor a user function holds in a closure, which :func:`needs_graph` cannot see): a walk
    over the graph's nodes, for code that asks its own results."""
    seen: set = set()
    stack = [out.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        leaf = getattr(node, "variable", None)  # an AccumulateGrad node holds its leaf
        if leaf is not None and leaf is not x:
            return True
        stack.extend(nxt for nxt, _ in node.next_functions)
    return False
