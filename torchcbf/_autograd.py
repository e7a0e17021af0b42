"""Whether a computation must record a graph: the test behind the fast paths that carry no
gradient and run only built-in code (the planner's C kernel, the estimators' Jacobians).
Code that calls user functions (the safety filter's real-time path) asks its own results
instead, since a user closure may hold a tensor that requires grad."""

from __future__ import annotations

import torch
from torch import Tensor, nn


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
