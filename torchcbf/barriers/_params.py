"""Helpers shared by the shapes: state indices and the device and dtype of a module."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import check_index, check_tensor

__all__ = ["StateIndex", "check_state", "float_spec"]


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
        return x[..., list(self.index)]

    def scatter(self, grad_p: Tensor, n: int) -> Tensor:
        """Embed a gradient w.r.t. the selected components ``[..., size]`` into ``[..., n]``."""
        out = grad_p.new_zeros(*grad_p.shape[:-1], n)
        out[..., list(self.index)] = grad_p
        return out

    def rows(self, s: Tensor) -> Tensor:
        """Selected rows of a matrix ``[..., n, q] -> [..., size, q]``."""
        if self._slice is not None:
            return s[..., self._slice, :]
        return s[..., list(self.index), :]


def float_spec(module: nn.Module) -> tuple[torch.device, torch.dtype]:
    """Device and dtype of the first floating tensor of ``module`` (CPU, default dtype if none)."""
    for tensor in list(module.parameters()) + list(module.buffers()):
        if tensor.is_floating_point():
            return tensor.device, tensor.dtype
    return torch.device("cpu"), torch.get_default_dtype()
