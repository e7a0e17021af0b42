"""Triton, where it imports: the GPU kernels' compiler (it ships with CUDA builds of torch).

Every Triton kernel of the library imports it from here; where it is missing the kernels are
not defined and their callers run torch code. On the CPU a kernel runs only under
``TRITON_INTERPRET=1`` (the tests use it).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import torch

try:
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the installation
    triton = None
    tl = None

__all__ = ["available", "interpreted", "location", "on_device", "tile", "tl", "triton"]


def available() -> bool:
    """Whether Triton imports."""
    return triton is not None


def interpreted() -> bool:
    """Whether Triton runs kernels in its interpreter (``TRITON_INTERPRET=1``: on the CPU)."""
    return os.environ.get("TRITON_INTERPRET") == "1"


def location() -> str | None:
    """Triton's version and where it is installed, or ``None`` where it does not import."""
    if triton is None:
        return None
    return f"triton {triton.__version__} at {Path(triton.__file__).parent}"


def tile(v: int) -> int:
    """The size of a kernel's tile axis holding ``v`` entries: the next power of two, at
    least 2."""
    return max(2, 1 << (max(v, 1) - 1).bit_length())


def on_device(t: torch.Tensor) -> contextlib.AbstractContextManager:
    """A context in which a kernel launched on ``t``'s data runs on ``t``'s CUDA device
    (Triton launches on the current device)."""
    return torch.cuda.device(t.device) if t.is_cuda else contextlib.nullcontext()
