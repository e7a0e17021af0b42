"""A function of CUDA tensors captured in a CUDA graph and replayed.

A call of small batched work on a GPU is often bound by the host: tens of launches, each a
few microseconds of Python and driver time, for kernels that finish sooner. Captured once
(:class:`CapturedCall`), the same work is one replay. What a graph fixes at capture: the
kernels, their launch shapes, the addresses of every tensor they read (the static inputs
and any tensor ``fn`` reads beside them) and every Python value ``fn`` turned into a kernel
argument. The caller recaptures when one of those changes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor


class _Slot(NamedTuple):
    """Where one output lies in its dtype's flat buffer."""

    dtype: torch.dtype
    start: int
    shape: torch.Size


def pack(outputs: Sequence[Tensor | None]) -> tuple[dict[torch.dtype, Tensor], list]:
    """``outputs`` concatenated into one flat tensor per dtype, and where each lies
    (``None`` for a ``None`` output): a copy of the outputs is then one copy per dtype."""
    parts: dict[torch.dtype, list[Tensor]] = {}
    sizes: dict[torch.dtype, int] = {}
    slots: list[_Slot | None] = []
    for t in outputs:
        if t is None:
            slots.append(None)
            continue
        slots.append(_Slot(t.dtype, sizes.get(t.dtype, 0), t.shape))
        parts.setdefault(t.dtype, []).append(t.reshape(-1))
        sizes[t.dtype] = sizes.get(t.dtype, 0) + t.numel()
    return {dtype: torch.cat(ts) for dtype, ts in parts.items()}, slots


def unpack(flat: dict[torch.dtype, Tensor], slots: list) -> tuple[Tensor | None, ...]:
    """The outputs of :func:`pack` as views of ``flat``."""
    return tuple(
        None if s is None else flat[s.dtype].narrow(0, s.start, s.shape.numel()).view(s.shape)
        for s in slots
    )


class CapturedCall:
    """``fn(*inputs) -> sequence of tensors (or None)`` captured in a CUDA graph.

    The capture runs ``fn`` once on static copies of ``inputs`` without executing it (run
    ``fn`` once uncaptured before, so that lazy set-up such as compiling a Triton kernel is
    done). Each call copies its tensors into the static inputs, replays the graph and
    returns copies of the outputs (a later replay overwrites the graph's own), made in one
    copy per dtype. ``fn`` may change tensors other than its inputs in place (a planner's
    plan, say): a replay does the same to the same storage. Raises what the capture raises
    (an operation that cannot be captured, such as a host synchronisation).
    """

    def __init__(self, fn: Callable[..., Sequence[Tensor | None]], inputs: Sequence[Tensor]):
        if not inputs or any(not t.is_cuda for t in inputs):
            raise ValueError("CapturedCall captures a function of CUDA tensors")
        self._inputs = tuple(t.clone() for t in inputs)
        self._graph = torch.cuda.CUDAGraph()
        # "thread_local": other threads' CUDA calls during the capture are theirs to make
        capture = torch.cuda.graph(self._graph, capture_error_mode="thread_local")
        with torch.cuda.device(inputs[0].device), capture:
            self._flat, self._slots = pack(fn(*self._inputs))

    def __call__(self, *inputs: Tensor) -> tuple[Tensor | None, ...]:
        if len(inputs) != len(self._inputs):
            raise ValueError(f"expected {len(self._inputs)} inputs, got {len(inputs)}")
        for i, (static, t) in enumerate(zip(self._inputs, inputs, strict=True)):
            if t.shape != static.shape or t.dtype != static.dtype or t.device != static.device:
                raise ValueError(
                    f"input {i} must be {static.dtype} {list(static.shape)} on "
                    f"{static.device} (as captured), got {t.dtype} {list(t.shape)} on {t.device}"
                )
            static.copy_(t)
        self._graph.replay()
        return unpack({dtype: t.clone() for dtype, t in self._flat.items()}, self._slots)
