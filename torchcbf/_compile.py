"""``torch.compile`` for the user code torchcbf evaluates (an MPPI cost), with a first call
short enough for a closed loop and an eager fallback where the backend fails.

Inductor's first CPU compile in a process normally builds and loads a test program for each
vector instruction set the CPU reports (AVX-512, AVX2, ...) and for each of its extensions
(AVX-512 BF16 and VNNI, AMX) before it generates any code: about 9-11 s of an 11-13 s first
call on a 2-core machine, each probe a C++ build plus a Python process that loads it. torch's
own kernels already run with the instruction sets the CPU and the operating system report
(``/proc/cpuinfo``), so during the first call of a compiled function (where it compiles)
inductor is told to trust that report: ``torch._inductor.config.cpp.vec_isa_ok = True`` for
the base sets and, for the extensions, whose probes that option does not cover, the probe
build (``VecISA.check_build``) answers yes for the duration of the call. Nothing is changed
where the user set ``vec_isa_ok`` (or ``TORCHINDUCTOR_VEC_ISA_OK``) themselves. The list is
computed once per process, so the first compile in the process decides it; later calls run
without the patch (it costs about 17 us, which a compiled step called once per horizon step
would pay 80 times). Where the C++ compiler cannot build for a reported extension, the
compile fails and the eager fallback below takes over.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from collections.abc import Callable, Iterator
from typing import Any

import torch

logger = logging.getLogger("torchcbf")


class Compiled:
    """``fn`` under ``torch.compile(fn, **options)``; eager ``fn`` from the first call on
    whose compilation fails in the backend (a C++ compiler that cannot build the generated
    code, say), with a warning. Errors of ``fn`` itself are raised as they are."""

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any]) -> None:
        self.eager = fn
        self.options = dict(options)
        self.compiled: Callable[..., Any] | None = torch.compile(fn, **options)
        self._first = True

    def __getstate__(self) -> dict[str, Any]:
        # the compiled function does not pickle: compile again where it is loaded
        return {"eager": self.eager, "options": self.options}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["eager"], state["options"])

    def __deepcopy__(self, memo: dict[int, Any]) -> Compiled:
        # compile the copy's function (a bound method: of the copied module)
        return Compiled(copy.deepcopy(self.eager, memo), self.options)

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            return self.eager(*args)
        from torch._dynamo.exc import BackendCompilerFailed
        from torch._inductor import config

        try:
            # the ISA list is computed once per process, on the first CPU compile
            if self._first and config.cpp.vec_isa_ok is None:
                with _trust_reported_isa():
                    out = self.compiled(*args)
            else:
                out = self.compiled(*args)
        except BackendCompilerFailed as err:
            logger.warning("torchcbf: torch.compile failed (%s); running eager", err)
            self.compiled = None
            return self.eager(*args)
        self._first = False
        return out


@contextlib.contextmanager
def _trust_reported_isa() -> Iterator[None]:
    """Inductor's instruction-set probes answered by the CPU's own report (module docstring)."""
    from torch._inductor import config, cpu_vec_isa

    probe = getattr(cpu_vec_isa.VecISA, "check_build", None)
    with config.patch({"cpp.vec_isa_ok": True}):
        if probe is None:
            yield
            return
        cpu_vec_isa.VecISA.check_build = lambda self, code: True  # type: ignore[method-assign]
        try:
            yield
        finally:
            cpu_vec_isa.VecISA.check_build = probe  # type: ignore[method-assign]
