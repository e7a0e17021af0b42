"""Triton, where it imports: the GPU kernels' compiler (it ships with CUDA builds of torch).

Every Triton kernel of the library imports it from here; where it is missing the kernels are
not defined and their callers run torch code. On the CPU a kernel runs only under
``TRITON_INTERPRET=1`` (the tests use it).
"""

from __future__ import annotations

import os
from pathlib import Path

try:
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the installation
    triton = None
    tl = None

__all__ = ["available", "interpreted", "location", "tl", "triton"]


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
