"""Input validation shared by every module: clear errors that name the argument and shapes."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def broadcast_shapes(*shapes: Sequence[int]) -> tuple[int, ...]:
    """The broadcast of ``shapes`` (as ``torch.broadcast_shapes``, ``RuntimeError`` if they do
    not broadcast). Pure Python on tuples of ints: ``torch.broadcast_shapes`` costs 10 to 60
    us per call, which is most of a small solve or filter call."""
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for shape in shapes:
        for i, d in enumerate(shape, start=ndim - len(shape)):
            if d == 1:
                continue
            if out[i] != 1 and out[i] != d:
                raise RuntimeError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
            out[i] = d
    return tuple(out)


def check_tensor(name: str, value: object) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a tensor; return it."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_last_dim(name: str, value: object, size: int) -> Tensor:
    """Check ``value`` is a tensor of shape ``[..., size]``."""
    value = check_tensor(name, value)
    if value.dim() == 0 or value.shape[-1] != size:
        raise ValueError(f"{name} must have shape [..., {size}], got {tuple(value.shape)}")
    return value


def check_batch_match(name_a: str, a: Tensor, name_b: str, b: Tensor, trailing: int = 1) -> None:
    """Check the leading (batch) dimensions of ``a`` and ``b`` broadcast together.

    ``trailing`` is the number of trailing non-batch dimensions of each tensor.
    """
    batch_a = a.shape[: a.dim() - trailing]
    batch_b = b.shape[: b.dim() - trailing]
    try:
        broadcast_shapes(batch_a, batch_b)
    except RuntimeError:
        raise ValueError(
            f"batch dimensions of {name_a} {tuple(a.shape)} and {name_b} {tuple(b.shape)} "
            "do not broadcast"
        ) from None


def check_positive(name: str, value: float) -> float:
    """Check a Python number is finite and > 0."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not value > 0 or value != value or value == float("inf"):
        raise ValueError(f"{name} must be a finite positive number, got {value}")
    return float(value)


def check_index(name: str, index: Sequence[int], state_dim: int | None) -> tuple[int, ...]:
    """Check a tuple of state indices is valid for ``state_dim`` (if known)."""
    index = tuple(int(i) for i in index)
    if len(index) == 0:
        raise ValueError(f"{name} must name at least one state component")
    if state_dim is not None and any(i < 0 or i >= state_dim for i in index):
        raise ValueError(f"{name}={index} is outside a state of size {state_dim}")
    if any(i < 0 for i in index):
        raise ValueError(f"{name}={index} must hold non-negative indices")
    return index


def as_tensor(name: str, value: object, *, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Convert a number, sequence or tensor to a floating tensor (default dtype if not a tensor)."""
    if isinstance(value, Tensor):
        out = value
        if not out.is_floating_point():
            out = out.to(torch.get_default_dtype())
        if dtype is not None or device is not None:
            out = out.to(device=device, dtype=dtype)
        return out
    try:
        return torch.as_tensor(value, dtype=dtype or torch.get_default_dtype(), device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name} must be a number, sequence or tensor, got {value!r}") from err


def check_spd(name: str, matrix: Tensor) -> Tensor:
    """Check a symmetric matrix ``[..., n, n]`` is positive definite (Cholesky succeeds)."""
    matrix = check_tensor(name, matrix)
    if matrix.dim() < 2 or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"{name} must be a square matrix [..., n, n], got {tuple(matrix.shape)}")
    if not torch.allclose(matrix, matrix.mT, atol=1e-8, rtol=1e-6):
        raise ValueError(f"{name} must be symmetric")
    _, info = torch.linalg.cholesky_ex(matrix)
    if bool((info != 0).any()):
        raise ValueError(f"{name} must be positive definite")
    return matrix
