"""CPU fast path of the dual active-set method: the C kernel ``_dual_kernel.c``.

The kernel is built at install time when a C compiler is present (``setup.py``) and is
called through :mod:`ctypes` (which releases the GIL, so a large batch is split over
``torch.get_num_threads()`` threads). It runs the algorithm of :mod:`torchcbf.qp._dual`
problem by problem, float64 on the CPU only; :func:`available` says whether it was built.
Without it, and on every other device, the torch implementation runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from torchcbf._native import check_operands, load_kernel, thread_pool

logger = logging.getLogger(__name__)

#: least work (``N^2 + M N`` per row, summed) a thread is given when a batch is split over
#: threads: 1,024 rows of N = 4, M = 8
MIN_WORK_PER_THREAD = 1024 * (4 * 4 + 8 * 4)
#: most variables the kernel handles (``NMAX`` in the C source)
MAX_VARS = 64
#: ``TORCHCBF_DUAL_KERNEL_VERSION`` of the C source this module calls (_dual_kernel.h)
KERNEL_VERSION = 9
#: the file name of the built kernel, without its extension suffix
KERNEL_STEM = "_dual_kernel"


@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    return load_kernel(
        Path(__file__).parent,
        KERNEL_STEM,
        "torchcbf_dual_version",
        KERNEL_VERSION,
        "using the torch solver",
        sources=("_dual_kernel.c",),
    )


def function(name: str) -> Callable[..., int] | None:
    """The kernel's exported function ``name`` (its types from the C source), or ``None``
    where the kernel is not built."""
    lib = _library()
    return None if lib is None else getattr(lib, name)


def can_certify() -> bool:
    """Whether :func:`certify` runs (the kernel is built)."""
    return available()


def available() -> bool:
    """Whether the C kernel was built and loads."""
    return _library() is not None


def applies(q: Tensor) -> bool:
    """Whether the kernel serves a problem batch with linear term ``q [B, N]``."""
    cpu64 = q.device.type == "cpu" and q.dtype == torch.float64
    return cpu64 and q.shape[-1] <= MAX_VARS and available()


def _kernel() -> ctypes.CDLL:
    lib = _library()
    if lib is None:
        raise RuntimeError("torchcbf: the QP kernel was not built (no C compiler at install)")
    return lib


def _run(fn: Callable[..., int], B: int, per_row: list[tuple[Tensor, int]], row_work: int) -> None:
    """Call ``fn(rows, *pointers)`` on chunks of the batch, in parallel for a large batch.

    ``per_row`` lists ``(tensor, elements per row)`` in argument order; each chunk gets
    pointers offset to its first row. ``row_work``: the work of one row (``N^2 + M N``)."""
    threads = max(1, min(torch.get_num_threads(), B * row_work // MIN_WORK_PER_THREAD))
    bounds = [B * k // threads for k in range(threads + 1)]

    def call(lo: int, hi: int) -> int:
        ptrs = [t.data_ptr() + lo * n * t.element_size() for t, n in per_row]
        return fn(hi - lo, *ptrs)

    if threads == 1:
        codes = [call(0, B)]
    else:
        codes = list(thread_pool(threads, "torchcbf-qp").map(call, bounds[:-1], bounds[1:]))
    if any(c != 0 for c in codes):
        raise MemoryError("torchcbf: the QP kernel could not allocate its workspace")


def _check_sizes(N: int, M: int) -> None:
    if not 1 <= N <= MAX_VARS or M < 1:
        raise ValueError(
            f"the QP kernel takes 1 to {MAX_VARS} variables and at least one row, got N={N}, M={M}"
        )


def forward(
    P: Tensor, q: Tensor, G: Tensor, h: Tensor, eps: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``(x [B,N], z [B,M], active [B,M], slots [B,N], L [B,N,N], ok [B], iterations [B],
    infeasible [B])`` for ``P [B,N,N], q [B,N], G [B,M,N], h [B,M]`` float64 on the CPU (see
    ``solve_dual``); ``infeasible`` marks rows proved infeasible by a Farkas certificate."""
    B, N = q.shape
    M = h.shape[-1]
    _check_sizes(N, M)
    operands = (("P", P, (B, N, N)), ("q", q, (B, N)), ("G", G, (B, M, N)), ("h", h, (B, M)))
    check_operands("the QP kernel", operands, dtype=torch.float64)
    P, q, G, h = (t.contiguous() for t in (P, q, G, h))
    x = q.new_empty(B, N)
    z = q.new_empty(B, M)
    active = torch.empty(B, M, dtype=torch.bool)
    slots = torch.empty(B, N, dtype=torch.int64)
    L = q.new_empty(B, N, N)
    ok = torch.empty(B, dtype=torch.bool)
    iters = torch.empty(B, dtype=torch.int64)
    infeasible = torch.empty(B, dtype=torch.bool)
    rows = [(P, N * N), (q, N), (G, M * N), (h, M)]
    outs = [(x, N), (z, M), (active, M), (slots, N), (L, N * N), (ok, 1), (iters, 1),
            (infeasible, 1)]  # fmt: skip
    fn = _kernel().torchcbf_dual_forward
    steps = min(max_iter, 2**31 - 1)  # a C int
    _run(lambda n, *a: fn(n, N, M, *a[:4], eps, steps, *a[4:]), B, rows + outs, N * N + M * N)
    return x, z, active, slots, L, ok, iters, infeasible


def backward(
    G: Tensor, L: Tensor, slots: Tensor, ok: Tensor, gx: Tensor, gz: Tensor
) -> tuple[Tensor, Tensor]:
    """Adjoints ``(w_x [B,N], wz [B,M])`` of the KKT system on the active slots (zeros on rows
    not ``ok``); the gradients follow by :func:`torchcbf.qp._kkt.input_gradients`."""
    B, M, N = G.shape
    _check_sizes(N, M)
    G, L, slots, ok, gx, gz = (t.contiguous() for t in (G, L, slots, ok, gx, gz))
    w_x = gx.new_empty(B, N)
    wz = gz.new_empty(B, M)
    fn = _kernel().torchcbf_dual_backward
    args = [(G, M * N), (L, N * N), (slots, N), (ok, 1), (gx, N), (gz, M), (w_x, N), (wz, M)]
    _run(lambda n, *a: fn(n, N, M, *a), B, args, N * N + M * N)
    return w_x, wz


def well_conditioned(L: Tensor, ok: Tensor, max_condition: float) -> Tensor:
    """``ok [B]`` and, per row, the condition estimate of the factor ``L [B,N,N]``
    (:func:`~torchcbf.qp._function.condition_estimate`) at most ``max_condition``."""
    B, N = L.shape[0], L.shape[-1]
    L = L.contiguous()
    out = ok.clone(memory_format=torch.contiguous_format)
    fn = _kernel().torchcbf_dual_check_condition
    _run(lambda n, l, o: fn(n, N, l, max_condition, o), B, [(L, N * N), (out, 1)], N * N * N)
    return out


def tight_rows(
    G: Tensor, h: Tensor, x: Tensor, active: Tensor, solved: Tensor, tight: float
) -> Tensor:
    """``active [B, M]`` plus the rows of ``solved`` problems tight at ``x`` (the rule of
    :func:`torchcbf.qp._kkt.with_tight_rows`) for ``G [B,M,N], h [B,M], x [B,N]``."""
    B, M, N = G.shape
    G, h, x, solved = (t.contiguous() for t in (G, h, x, solved))
    out = active.clone(memory_format=torch.contiguous_format)
    fn = _kernel().torchcbf_dual_tight_rows
    rows = [(G, M * N), (h, M), (x, N), (solved, 1), (out, M)]
    _run(lambda n, g, hh, xx, s, o: fn(n, N, M, g, hh, xx, s, tight, o), B, rows, M * N)
    return out


def certify(
    P: Tensor,
    q: Tensor,
    G: Tensor,
    h: Tensor,
    todo: Tensor,
    x: Tensor,
    z: Tensor,
    active: Tensor,
    converged: Tensor,
    *,
    eps: float,
    max_iter: int,
    prox_weight: float,
    prox_steps: int,
    rounding: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(x [B,N], z [B,M], certified [B])``: the rows ``todo [B]`` the dual method left
    (its answer ``x, z``, active set ``active [B,M]``, ``converged [B]``) certified as in
    :func:`torchcbf.qp._function._certify_ill_conditioned` for ``P [B,N,N], q [B,N],
    G [B,M,N], h [B,M]`` float64 on the CPU: the method's own point, the solution on its
    active set, or on the active set of up to ``prox_steps`` proximal steps, kept where it
    is a KKT point to rounding and ``P - tau I`` is positive definite or ``q'x >= 0`` (no
    certificate of unboundedness can exist; ``rounding``: the inputs' unit roundoff). Rows
    not certified keep ``x, z`` as given."""
    B, N = q.shape
    M = h.shape[-1]
    _check_sizes(N, M)
    fn = _kernel().torchcbf_dual_certify
    P, q, G, h, todo, active, converged = (
        t.contiguous() for t in (P, q, G, h, todo, active, converged)
    )
    x = x.clone(memory_format=torch.contiguous_format)
    z = z.clone(memory_format=torch.contiguous_format)
    certified = torch.zeros(B, dtype=torch.bool)
    steps = min(max_iter, 2**31 - 1)
    rows = [(P, N * N), (q, N), (G, M * N), (h, M), (todo, 1), (active, M), (converged, 1)]
    outs = [(x, N), (z, M), (certified, 1)]

    def call(n: int, *a: int) -> int:
        return fn(n, N, M, *a[:7], eps, steps, prox_weight, prox_steps, rounding, *a[7:])

    _run(call, B, rows + outs, N * N + M * N)
    return x, z, certified
