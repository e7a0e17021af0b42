"""Helpers shared by the shapes: state indices and the device and dtype of a module."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import check_index, check_tensor

__all__ = ["StateIndex", "check_state", "float_spec", "take"]


def take(x: Tensor, index: Sequence[int], dim: int = -1) -> Tensor:
    """``x`` at the positions ``index`` along ``dim < 0``, as one stack of views (indexing
    with a list copies the list to the device, and waits for the copy, on every call)."""
    return torch.stack([x.select(dim, i) for i in index], dim)


def embed(part: Tensor, index: Sequence[int], n: int, dim: int = -1) -> Tensor:
    """``part`` (size ``len(index)`` along ``dim < 0``) placed at the positions ``index`` of
    a size-``n`` axis, zeros elsewhere (the inverse of :func:`take`, without a list index)."""
    where = {i: k for k, i in enumerate(index)}
    zero = torch.zeros_like(part.select(dim, 0))
    return torch.stack([part.select(dim, where[i]) if i in where else zero for i in range(n)], dim)


def check_state(name: str, x: object, index: tuple[int, ...], state_dim: int | None) -> Tensor:
    """Check a state ``[..., n]`` holds every index (and has size ``state_dim`` if given)."""
    x = check_tensor(name, x)
    if x.dim() == 0:
        raise ValueError(f"{name} must have shape [..., n], got a scalar")
    n = x.shape[-1]
    if state_dim is not None and n != state_dim:
        raise ValueError(f"{name} must have shape [..., {state_dim}], got {tuple(x.shape)}")
    if max(index) >= n:
        raise ValueError(f"index={index} is outside a state of size {n} ({name} {tuple(x.shape)})")
    return x


class StateIndex:
    """Select state components ``x[..., index]`` (a slice when the indices are contiguous)."""

    def __init__(self, index: Sequence[int] | None, size: int, state_dim: int | None) -> None:
        if index is None:
            index = tuple(range(size))
        self.index = check_index("index", index, state_dim)
        if len(self.index) != size:
            raise ValueError(
                f"index={self.index} must name {size} state components (one per coordinate)"
            )
        lo = self.index[0]
        contiguous = self.index == tuple(range(lo, lo + size))
        self._slice = slice(lo, lo + size) if contiguous else None
        self.state_dim = state_dim

    def __call__(self, x: Tensor) -> Tensor:
        """``x [..., n] -> [..., size]``."""
        check_state("x", x, self.index, self.state_dim)
        if self._slice is not None:
            return x[..., self._slice]
        return take(x, self.index)

    def scatter(self, grad_p: Tensor, n: int) -> Tensor:
        """Embed a gradient w.r.t. the selected components ``[..., size]`` into ``[..., n]``."""
        return embed(grad_p, self.index, n)

    def rows(self, s: Tensor) -> Tensor:
        """Selected rows of a matrix ``[..., n, q] -> [..., size, q]``."""
        if self._slice is not None:
            return s[..., self._slice, :]
        return take(s, self.index, -2)


def float_spec(module: nn.Module) -> tuple[torch.device, torch.dtype]:
    """Device and dtype of the first floating tensor of ``module`` (CPU, default dtype if none)."""
    for tensor in list(module.parameters()) + list(module.buffers()):
        if tensor.is_floating_point():
            return tensor.device, tensor.dtype
    return torch.device("cpu"), torch.get_default_dtype()
