"""Loading the optional C kernels (built by ``setup.py``), the threads that run them, and
the C library's heap settings that large torch workloads on the CPU depend on.

Each kernel is a plain C library next to the module that calls it through ctypes, with a
``<prefix>_version()`` function; the argument and return types of its exported functions
are read from its C source (:func:`prototypes`). A library that is missing, does not
load, or was built from another version of its source (an editable install not rebuilt
after an edit) is refused with a warning naming what runs instead, and the caller falls
back to its torch code.
"""

from __future__ import annotations

import ast
import ctypes
import functools
import importlib.machinery
import logging
import operator
import os
import platform
import re
from collections.abc import Callable, Iterable, Sequence
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


#: C types of the kernels' exported signatures (pointers and arrays are ``c_void_p``)
_C_TYPES: dict[str, Any] = {
    "int": ctypes.c_int,
    "int32_t": ctypes.c_int32,
    "int64_t": ctypes.c_int64,
    "uint64_t": ctypes.c_uint64,
    "size_t": ctypes.c_size_t,
    "double": ctypes.c_double,
    "float": ctypes.c_float,
}
#: what ``REAL`` stands for in a function named ``SUFFIX(name)`` (a body included once per
#: precision, as the rollout kernel's)
_PRECISIONS = {"_f32": "float", "_f64": "double"}
#: the start of an exported definition: its return type and name, up to its ``(``
_EXPORT = re.compile(r"^(\w+)\s+(SUFFIX\()?(torchcbf_\w+)\)?\s*\(", re.MULTILINE)
_COMMENTS = re.compile(r"/\*.*?\*/|//[^\n]*", re.DOTALL)


def _c_type(decl: str, real: str, where: str) -> Any:
    """The ctypes type of one parameter or return declaration (without its name)."""
    if "*" in decl or "[" in decl:
        return ctypes.c_void_p
    base = " ".join(w for w in decl.split() if w != "const")
    base = real if base == "REAL" else base
    if base in _C_TYPES:
        return _C_TYPES[base]
    if base.endswith("_kernel"):  # a function-pointer typedef of the sources
        return ctypes.c_void_p
    raise ValueError(f"{where}: the C type {decl!r} has no ctypes mapping in torchcbf._native")


def prototypes(sources: Iterable[Path]) -> dict[str, tuple[list[Any], Any]]:
    """The ctypes ``(argtypes, restype)`` of every function a kernel exports (a definition
    ``<type> torchcbf_...(...) {`` at the start of a line of its C ``sources``, comments
    aside): the C source is the one statement of each interface. A function named
    ``SUFFIX(name)`` gives ``name_f32`` and ``name_f64`` with ``REAL`` as ``float`` and
    ``double``. Pointers, arrays and the sources' ``*_kernel`` function-pointer types are
    ``c_void_p``; any other type without a mapping raises ``ValueError``."""
    found: dict[str, tuple[list[Any], Any]] = {}
    for source in sources:
        text = _COMMENTS.sub(" ", source.read_text())
        for match in _EXPORT.finditer(text):
            ret, suffixed, name = match.groups()
            depth, end = 1, match.end()
            while depth:  # the parameters, to their closing parenthesis
                depth += {"(": 1, ")": -1}.get(text[end], 0)
                end += 1
            if not text[end:].lstrip().startswith("{"):
                continue  # a declaration, not the definition
            params = text[match.end() : end - 1]
            where = f"{source.name}: {name}"
            variants = _PRECISIONS.items() if suffixed else [("", "REAL")]
            for suffix, real in variants:
                types = []
                for param in (p.strip() for p in params.split(",")):
                    if param in ("", "void"):
                        continue
                    decl = param if "*" in param or "[" in param else param.rsplit(None, 1)[0]
                    types.append(_c_type(decl, real, where))
                restype = None if ret == "void" else _c_type(ret, real, where)
                found[name + suffix] = (types, restype)
    return found


_DEFINE = re.compile(r"^\s*#define\s+(\w+)\s+(0|[1-9]\d*)\s*$", re.MULTILINE)
_ENUM = re.compile(r"\benum\s*(?:\w+\s*)?\{([^}]*)\}")


def _integer(expression: str, names: dict[str, int], where: str) -> int:
    """The value of a C integer expression of literals, known names, ``+`` and ``*``."""

    def value(node: ast.AST) -> int:
        if isinstance(node, ast.Constant) and type(node.value) is int:
            return node.value
        if isinstance(node, ast.Name) and node.id in names:
            return names[node.id]
        if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Mult)):
            left, right = value(node.left), value(node.right)
            return left + right if isinstance(node.op, ast.Add) else left * right
        raise ValueError(f"{where}: cannot evaluate {expression!r}")

    try:
        tree = ast.parse(expression, mode="eval")
    except SyntaxError:
        raise ValueError(f"{where}: cannot evaluate {expression!r}") from None
    return value(tree.body)


def constants(sources: Iterable[Path]) -> dict[str, int]:
    """The integer constants of C ``sources``: each ``#define NAME <decimal integer>`` and
    each member of an ``enum [name] { ... }`` (comments aside), an enum member's value given
    as an expression of decimal integers, ``+``, ``*`` and earlier names, or one more than
    the member before it (anything else in an enum raises ``ValueError``). What a kernel's
    configuration vector holds where (its field offsets, record sizes and codes) is read
    from here, so the C source is its one statement."""
    found: dict[str, int] = {}
    for source in sources:
        text = _COMMENTS.sub(" ", source.read_text())
        found.update((name, int(value)) for name, value in _DEFINE.findall(text))
        for body in _ENUM.findall(text):
            value = -1
            for item in (part.strip() for part in body.split(",")):
                if not item:
                    continue
                name, _, expression = (w.strip() for w in item.partition("="))
                if expression:
                    value = _integer(expression, found, f"{source.name}: {item!r}")
                else:
                    value += 1
                found[name] = value
    return found


class Layout(dict[str, int]):
    """The integer constants of a kernel's C sources (:func:`constants`), with the records
    they describe: a record's size is one constant and its fields are the constants named
    with one prefix (``TR_TYPE``, ``TR_IDX``, ...), each the offset where it starts and
    running to the next field of that prefix."""

    def __init__(self, values: dict[str, int]) -> None:
        super().__init__(values)
        offsets: dict[str, list[int]] = {}
        for name, at in self.items():
            offsets.setdefault(name.split("_", 1)[0], []).append(at)
        #: each name's offset and the offset of the next field with its prefix (None: last)
        self.spans: dict[str, tuple[int, int | None]] = {
            name: (at, min((v for v in offsets[name.split("_", 1)[0]] if v > at), default=None))
            for name, at in self.items()
        }

    @classmethod
    def read(cls, sources: Iterable[Path]) -> Layout:
        return cls(constants(sources))

    def record(
        self, size: str, *, cast: type = float, **fields: float | Sequence[float]
    ) -> list[Any]:
        """A record of ``self[size]`` values (``cast`` of each) with each field set (a list or
        tuple from its offset on), the rest zero; ``ValueError`` for a field that runs into
        the next one."""
        rec = [cast(0)] * self[size]
        spans = self.spans
        for name, value in fields.items():
            at, end = spans[name]
            limit = len(rec) if end is None or end > len(rec) else end
            if not isinstance(value, (list, tuple)):  # one value (the common case, quick)
                if at >= limit:
                    raise ValueError(f"the field {name} does not fit in {size}")
                rec[at] = cast(value)
                continue
            if at + len(value) > limit:
                raise ValueError(f"{len(value)} values do not fit the field {name} of {size}")
            rec[at : at + len(value)] = [cast(v) for v in value]
        return rec

    def packer(self, size: str, *names: str) -> Callable[..., list[Any]]:
        """A quick ``pack(*values)``: the record of ``self[size]`` slots with the one-slot
        field ``names[i]`` set to ``values[i]`` and the other slots 0 (for records built on
        a hot path)."""
        n = self[size]
        slots = [len(names)] * n  # the index of the 0 appended to the values
        for i, name in enumerate(names):
            at, end = self.spans[name]
            if at >= n or (n if end is None else end) - at != 1:
                raise ValueError(f"{name} is not a one-slot field of {size}")
            slots[at] = i
        get = operator.itemgetter(*slots, len(names))  # two items at least: always a tuple

        def pack(*values: Any) -> list[Any]:
            return list(get((*values, 0)))[:n]

        return pack

    def field(self, rec: Sequence[float], name: str, count: int | None = None) -> Any:
        """The field ``name`` of a record: one value, or the ``count`` values from its
        offset."""
        at = self[name]
        return rec[at] if count is None else list(rec[at : at + count])


def load_kernel(
    directory: Path,
    stem: str,
    version_symbol: str,
    version: int,
    fallback: str,
    sources: Iterable[str] = (),
):
    """The ctypes library ``directory/stem<extension suffix>`` if it exists, loads and
    reports ``version``, else ``None`` with a warning ending in ``fallback`` (e.g. "MPPI runs
    in torch"); callers cache the answer, so each kernel warns once per process. The
    exported functions get their argument and return types from the C ``sources`` (file
    names in ``directory``, :func:`prototypes`); a library whose sources cannot be read is
    refused the same way."""
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
    try:
        interface = prototypes(directory / name for name in sources)
    except OSError as err:
        logger.warning("torchcbf: cannot read the interface of %s (%s); %s", path, err, fallback)
        return None
    for name, (argtypes, restype) in interface.items():
        function = getattr(lib, name, None)
        if function is None:
            logger.warning(
                "torchcbf: %s does not export %s, which its source defines; %s (reinstall to "
                "rebuild it)",
                path,
                name,
                fallback,
            )
            return None
        function.argtypes, function.restype = argtypes, restype
    return lib


def kernel_file(directory: Path, stem: str) -> Path | None:
    """The built library ``directory/stem<extension suffix>``, or ``None``."""
    found = (directory / f"{stem}{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES)
    return next((path for path in found if path.exists()), None)


def check_operands(
    where: str,
    operands: Iterable[tuple[str, Tensor | None, tuple[int, ...]]],
    *,
    dtype: torch.dtype | None = None,
) -> None:
    """Raise ``ValueError`` naming the operand of a kernel call that is not what the kernel
    reads: each ``(name, tensor, shape)`` (``None``: absent) a CPU tensor of exactly
    ``shape``, of ``dtype`` where given (else any floating dtype, cast by
    :func:`float64_pointers`)."""
    for name, t, shape in operands:
        if t is None:
            continue
        if t.device.type != "cpu":
            raise ValueError(f"{where}: {name} must be a CPU tensor, got one on {t.device}")
        if (dtype is not None and t.dtype != dtype) or not t.is_floating_point():
            raise ValueError(f"{where}: {name} must be {dtype or 'floating'}, got {t.dtype}")
        if tuple(t.shape) != shape:
            raise ValueError(f"{where}: {name} must have shape {list(shape)}, got {list(t.shape)}")


def float64_pointers(tensors: Iterable[Tensor | None]) -> tuple[list[int], list[Tensor]]:
    """The data pointers of ``tensors`` as contiguous float64 CPU memory for a kernel (0, a
    NULL pointer, for ``None``), and the tensors they point into (copies where a tensor was
    of another dtype, strided or a negated view): the caller keeps that list alive through
    the call."""
    f64 = torch.float64
    pointers = []
    held = []
    for v in tensors:
        if v is None:
            pointers.append(0)
            continue
        if v.dtype is not f64 or not v.is_contiguous() or v.is_neg():
            v = v.detach().resolve_neg().to(f64).contiguous()
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
