"""Loading the optional C kernels (built by ``setup.py``), the threads that run them, and
the C library's heap settings that large torch workloads on the CPU depend on.

Each kernel is a plain C library next to the module that calls it through ctypes, with a
``<prefix>_version()`` function. A library that is missing, does not load, or was built from
another version of its source (an editable install not rebuilt after an edit) is refused
with a warning naming what runs instead, and the caller falls back to its torch code.
"""

from __future__ import annotations

import ctypes
import functools
import importlib.machinery
import logging
import os
import platform
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

logger = logging.getLogger("torchcbf")

#: the kernels' code of each model kind (:class:`torchcbf.dynamics.NativeModel`)
MODEL_CODES: dict[str, int] = {
    "single_integrator": 0,
    "double_integrator": 1,
    "unicycle": 2,
    "accel_unicycle": 3,
}


def model_code(dynamics: object) -> tuple[int, int] | None:
    """``(code, dim)`` of a model's :meth:`~torchcbf.dynamics.ControlAffine.native_model`
    for the kernels, or ``None`` where torch must evaluate it."""
    native = getattr(dynamics, "native_model", None)
    found = None if native is None else native()
    if found is None or found.kind not in MODEL_CODES:
        return None
    return MODEL_CODES[found.kind], int(found.dim)


def load_kernel(
    directory: Path,
    stem: str,
    version_symbol: str,
    version: int,
    fallback: str,
    signatures: dict[str, list[Any]] | None = None,
):
    """The ctypes library ``directory/stem<extension suffix>`` if it exists, loads and
    reports ``version``, else ``None`` with a warning ending in ``fallback`` (e.g. "MPPI runs
    in torch"); callers cache the answer, so each kernel warns once per process.
    ``signatures`` maps each exported function to its argument types; all return ``int``."""
    path = kernel_file(directory, stem)
    if path is None:
        logger.warning(
            "torchcbf: the C kernel %s is not built (no %s.* next to %s: no C compiler at "
            "install?); %s",
            stem,
            stem,
            directory,
            fallback,
        )
        return None
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as err:
        logger.warning("torchcbf: cannot load %s (%s); %s", path, err, fallback)
        return None
    found = getattr(lib, version_symbol, None)
    if found is None or found() != version:
        logger.warning(
            "torchcbf: %s was built from another version of %s.c; %s (reinstall to rebuild it)",
            path,
            stem,
            fallback,
        )
        return None
    for name, argtypes in (signatures or {}).items():
        function = getattr(lib, name)
        function.argtypes, function.restype = argtypes, ctypes.c_int
    return lib


def kernel_file(directory: Path, stem: str) -> Path | None:
    """The built library ``directory/stem<extension suffix>``, or ``None``."""
    found = (directory / f"{stem}{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES)
    return next((path for path in found if path.exists()), None)


def float64_pointers(tensors: Iterable[Tensor | None]) -> tuple[list[int], list[Tensor]]:
    """The data pointers of ``tensors`` as contiguous float64 CPU memory for a kernel (0, a
    NULL pointer, for ``None``), and the tensors they point into (copies where a tensor was
    of another dtype or strided): the caller keeps that list alive through the call."""
    f64 = torch.float64
    pointers = []
    held = []
    for v in tensors:
        if v is None:
            pointers.append(0)
            continue
        if v.dtype is not f64 or not v.is_contiguous():
            v = v.detach().to(f64).contiguous()
        held.append(v)
        pointers.append(v.data_ptr())
    return pointers, held


def thread_pool(threads: int, name: str) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads for kernel calls (the GIL is released in them), one per
    process: a forked child inherits the pool object but not its threads."""
    return _pool(threads, name, os.getpid())


@functools.lru_cache(maxsize=16)
def _pool(threads: int, name: str, pid: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix=name)


#: a block of this size, allocated and freed once, raises glibc's dynamic thresholds to it
HEAP_PRIMER_BYTES = 24 << 20


@functools.cache
def keep_freed_heap() -> bool:
    """Let glibc keep freed blocks of up to ``HEAP_PRIMER_BYTES`` for reuse (once per process;
    ``True`` where it applied).

    glibc serves blocks above its mmap threshold (128 KiB at start) with fresh mappings and
    hands the top of its heap back to the kernel once more than its trim threshold is free.
    A torch cost evaluated slice by slice allocates and frees intermediates of a few MB per
    slice, so every slice page-faults its memory in again (up to 10^5 faults, 2x the time,
    per MPPI call). Freeing one mapped block of ``HEAP_PRIMER_BYTES`` raises both thresholds
    the way glibc does for any program that frees such a block (mmap threshold to its size,
    trim threshold to twice that); the process then keeps up to about 48 MB of freed memory
    for reuse instead of returning it. Elsewhere (other C libraries, other systems) nothing
    is done.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        malloc, free = libc.malloc, libc.free
    except (OSError, AttributeError):
        return False
    malloc.restype, malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    free.restype, free.argtypes = None, [ctypes.c_void_p]
    block = malloc(HEAP_PRIMER_BYTES)
    if not block:
        return False
    free(block)
    return True
