"""The safety filter's real-time path: up to :data:`MAX_BATCH` states on the CPU, in one C call.

A robot calls the filter on one state per control tick; there the time goes into the
number of operations around the solve, not the solve. Given the conditions (tensors from
:class:`~torchcbf.filters.SafetyFilter`'s Lie terms), :func:`solve` assembles the filter QP
(as :func:`torchcbf.filters.qp_data.assemble` documents it), solves it with the dual
active-set kernel and computes the residuals and statuses in the C kernel
``_filter_kernel.c``. It answers only when every row is certified; otherwise it returns
``None`` and the caller runs the general path, which gives the same answers there.
"""

from __future__ import annotations

import ctypes
import functools
import math
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._native import float64_pointers, load_kernel
from torchcbf.barriers import native
from torchcbf.qp import realtime as qp_realtime

#: ``100 FILTER_KERNEL_VERSION + TORCHCBF_DUAL_KERNEL_VERSION`` of the C sources this module
#: calls (the filter's kernel carries the QP kernel's solver)
KERNEL_VERSION = 100 * 11 + qp_realtime.KERNEL_VERSION
#: the file name of the built kernel, without its extension suffix
KERNEL_STEM = "_filter_kernel"
#: most states the path takes: on one thread the kernel, a state after another, beats the
#: batched torch path up to about this size (scenario B's filter: 0.13 against 0.95 ms on 32
#: states, 0.87 against 2.7 ms on 1,024; scripts/bench_filters.py), and a batch it declines
#: costs its general-path time again
MAX_BATCH = 1024
#: the kernel's codes of the CBF slack modes
SLACK_CODES = {"none": 0, "shared": 1, "per_row": 2}


@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    return load_kernel(
        Path(__file__).parent,
        KERNEL_STEM,
        "torchcbf_filter_version",
        KERNEL_VERSION,
        "the safety filter takes its general path on every batch",
        sources=("_filter_kernel.c", "../barriers/_lie_kernel.h"),
    )


def available() -> bool:
    """Whether the filter kernel was built and loads."""
    return _library() is not None


def inputs_finite(x: Tensor, u: Tensor, t: Tensor) -> bool:
    """Whether the CPU tensors ``x``, ``u`` and ``t`` hold no NaN and no infinity (one kernel
    call for contiguous float64 tensors)."""
    lib = _library()
    f64 = torch.float64
    if (
        lib is not None
        and x.dtype is f64 and u.dtype is f64 and t.dtype is f64
        and x.is_contiguous() and u.is_contiguous() and t.is_contiguous()
    ):  # fmt: skip
        return bool(lib.torchcbf_filter_inputs_finite(
            x.numel(), x.data_ptr(), u.numel(), u.data_ptr(), t.numel(), t.data_ptr()
        ))  # fmt: skip
    return all(bool(torch.isfinite(v).all()) for v in (x, u, t))


class RealtimeOutput(NamedTuple):
    """The filter's answer (float64) with the batch shape ``[...]`` asked for: ``u [..., m]``,
    ``slack [..., k + c]``, ``value [..., k + c]`` (as in
    :class:`~torchcbf.filters.FilterOutput`) and int64 ``status [...]`` (``SOLVED`` or
    ``RELAXED``)."""

    u: Tensor
    slack: Tensor
    value: Tensor
    status: Tensor


def solve(
    cbf: tuple[Tensor, Tensor] | native.ConditionCall | None,
    clf: tuple[Tensor, Tensor] | None,
    u_nom: Tensor,
    R: Tensor,
    lo: Tensor | None,
    hi: Tensor | None,
    *,
    slack: str,
    two_pass: bool,
    cbf_weight: float,
    clf_weight: float,
    eps: float,
    max_iter: int,
    slack_tol: float,
    batch: tuple[int, ...] | None = None,
) -> RealtimeOutput | None:
    """The filter QP of ``B`` states from the conditions ``cbf = (a [B,k,m], b [B,k])``
    (``a . u + b >= 0``) and ``clf = (a [B,c,m], b [B,c])`` (``a . u + b <= delta``), with
    ``u_nom [B, m]``, ``R [m, m]`` and limits ``lo, hi [m]`` (``None`` or infinite where
    absent), CPU tensors without grad. ``cbf`` may also be a prepared call of the Lie-term
    kernel (:func:`torchcbf.barriers.native.condition_call`): the kernel then computes the
    conditions in the same C call (and writes its ``h``). ``two_pass``: also solve the hard
    QP and prefer its answer (see :class:`~torchcbf.filters.SafetyFilter`'s ``exact``).
    States, times and ``u_nom`` are the caller's to check (:func:`inputs_finite`, before any
    computation). The outputs have the batch shape ``batch`` (default ``(B,)``).

    Returns ``None`` when a tensor has another shape than these, when a condition is not
    finite, or when the kernel does not certify every row (the caller then takes the
    general path)."""
    lib = _library()
    if lib is None:
        return None
    B, m = u_nom.shape
    call = cbf if isinstance(cbf, native.ConditionCall) else None
    if call is not None:
        k = sum(call.sizes)
        cbf = None
        if call.h.shape != (B, k):
            raise ValueError(
                f"the prepared condition call is for h of shape {tuple(call.h.shape)}, "
                f"u_nom has {B} rows"
            )
    else:
        k = 0 if cbf is None else cbf[1].shape[1]
    c = 0 if clf is None else clf[1].shape[1]
    if (
        R.shape != (m, m)
        or (lo is not None and lo.shape != (m,))
        or (hi is not None and hi.shape != (m,))
        or (cbf is not None and (cbf[0].shape != (B, k, m) or cbf[1].shape != (B, k)))
        or (clf is not None and (clf[0].shape != (B, c, m) or clf[1].shape != (B, c)))
        or (batch is not None and math.prod(batch) != B)
    ):
        return None  # not the layout the kernel reads: the general path answers
    shape = (B,) if batch is None else batch
    conditions = (None, None) if cbf is None else cbf
    conditions += (None, None) if clf is None else clf
    # `held`: the tensors the pointers read, alive through the call
    pointers, held = float64_pointers((*conditions, u_nom, R, lo, hi))
    f64 = torch.float64
    u = torch.empty(*shape, m, dtype=f64)
    slk = torch.empty(*shape, k + c, dtype=f64)
    value = torch.empty(*shape, k + c, dtype=f64)
    status = torch.empty(shape, dtype=torch.int64)
    options = (
        cbf_weight, clf_weight, eps, min(max_iter, 2**31 - 1), slack_tol,
        qp_realtime.MAX_DUAL_CONDITION,
        u.data_ptr(), slk.data_ptr(), value.data_ptr(), status.data_ptr(),
    )  # fmt: skip
    sizes = B, m, k, c, SLACK_CODES[slack], int(two_pass)
    if call is None:
        code = lib.torchcbf_filter_solve(*sizes, *pointers, *options)
    else:
        code = lib.torchcbf_filter_quadrics(
            native.kernel_address(), native.KERNEL_VERSION, call.meta.buffer_info()[0],
            call.reals.buffer_info()[0], call.pointers.buffer_info()[0], *sizes, *pointers[2:],
            *options,
        )  # fmt: skip
    if code < 0:
        raise MemoryError("torchcbf: the safety filter's kernel could not allocate its workspace")
    if code:
        return None
    return RealtimeOutput(u, slk, value, status)
