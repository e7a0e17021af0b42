"""``torch.compile`` for the user code torchcbf evaluates (an MPPI cost), with a first call
short enough for a closed loop and an eager fallback where the backend fails.

Inductor's first CPU compile in a process normally builds and loads a test program for each
vector instruction set the CPU reports (AVX-512, AVX2, ...) before it generates any code:
about 10 s of a 13 s first call on a 2-core machine. torch's own kernels already run with
the instruction set the CPU and the operating system support (``/proc/cpuinfo``), so while
the compiled function compiles, inductor is told to trust that list
(``torch._inductor.config.cpp.vec_isa_ok = True``), unless the user set that option (or
``TORCHINDUCTOR_VEC_ISA_OK``) themselves. The list is computed once per process, so the
first compile in the process decides it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

logger = logging.getLogger("torchcbf")


class Compiled:
    """``fn`` under ``torch.compile(fn, **options)``; eager ``fn`` from the first call on
    whose compilation fails in the backend (a C++ compiler that cannot build the generated
    code, say), with a warning. Errors of ``fn`` itself are raised as they are."""

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any]) -> None:
        self.eager = fn
        self.compiled: Callable[..., Any] | None = torch.compile(fn, **options)

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            return self.eager(*args)
        from torch._dynamo.exc import BackendCompilerFailed
        from torch._inductor import config

        try:
            if config.cpp.vec_isa_ok is not None:  # the user's choice
                return self.compiled(*args)
            with config.patch({"cpp.vec_isa_ok": True}):
                return self.compiled(*args)
        except BackendCompilerFailed as err:
            logger.warning("torchcbf: torch.compile failed (%s); running eager", err)
            self.compiled = None
            return self.eager(*args)
