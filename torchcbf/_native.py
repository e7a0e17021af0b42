"""Loading the optional C kernels (built by ``setup.py``) and the threads that run them.

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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

logger = logging.getLogger("torchcbf")


def load_kernel(directory: Path, stem: str, version_symbol: str, version: int, fallback: str):
    """The ctypes library ``directory/stem<extension suffix>`` if it loads and reports
    ``version``, else ``None`` (with a warning ending in ``fallback``, e.g. "MPPI runs in
    torch")."""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = directory / f"{stem}{suffix}"
        if not path.exists():
            continue
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
        return lib
    return None


def thread_pool(threads: int, name: str) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads for kernel calls (the GIL is released in them), one per
    process: a forked child inherits the pool object but not its threads."""
    return _pool(threads, name, os.getpid())


@functools.lru_cache(maxsize=16)
def _pool(threads: int, name: str, pid: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix=name)
