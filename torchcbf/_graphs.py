"""A function of CUDA tensors captured in a CUDA graph and replayed.

A call of small batched work on a GPU is often bound by the host: tens of launches, each a
few microseconds of Python and driver time, for kernels that finish sooner. Captured once
(:class:`CapturedCall`), the same work is one replay. What a graph fixes at capture: the
kernels, their launch shapes, the addresses of every tensor they read (the static inputs
and any tensor ``fn`` reads beside them) and every Python value ``fn`` turned into a kernel
argument. The caller captures again when one of those changes.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Sequence
from typing import ClassVar

import torch
from torch import Tensor


def _copies(outputs: Sequence[Tensor | None]) -> tuple[Tensor | None, ...]:
    """Contiguous copies of ``outputs`` (``None`` kept), each with storage of its own, made
    by one multi-tensor copy per dtype and device (on a GPU a launch each, not one per
    output)."""
    copies = [
        None if t is None else torch.empty_like(t, memory_format=torch.contiguous_format)
        for t in outputs
    ]
    groups: dict[tuple[torch.dtype, torch.device], tuple[list[Tensor], list[Tensor]]] = {}
    for t, c in zip(outputs, copies, strict=True):
        if t is not None and c is not None:
            dst, src = groups.setdefault((t.dtype, t.device), ([], []))
            dst.append(c)
            src.append(t)
    for dst, src in groups.values():
        torch._foreach_copy_(dst, src)
    return tuple(copies)


class CapturedCall:
    """``fn(*inputs) -> sequence of tensors (or None)``, run once and captured in a CUDA
    graph.

    The constructor copies ``inputs`` into static tensors and, on a stream of its own on
    their device, runs ``fn`` on them for real (the warm-up PyTorch's recipe asks for: lazy
    set-up such as a Triton kernel's compilation for these exact inputs happens here; its
    outputs are this call's answer, :attr:`first`), then captures it. A capture that fails
    (an operation a graph cannot hold, such as a host synchronisation) leaves
    :attr:`error` set and the call unusable; the warm-up's answer stands. Each later call
    copies its tensors into the static inputs, replays the graph on the current stream and
    returns copies of the outputs (a later replay overwrites the graph's own). ``fn`` may
    change tensors other than its inputs in place (a planner's plan, say): a replay does the
    same to the same storage. One capture runs at a time in a process.
    """

    #: captures share process-wide state (the allocator's capture mode): one at a time
    _capturing: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, fn: Callable[..., Sequence[Tensor | None]], inputs: Sequence[Tensor]):
        if not inputs or any(not t.is_cuda for t in inputs):
            raise ValueError("CapturedCall captures a function of CUDA tensors")
        self.error: Exception | None = None
        self._graph: torch.cuda.CUDAGraph | None = None
        device = inputs[0].device
        with self._capturing, torch.cuda.device(device), torch.inference_mode(False):
            current = torch.cuda.current_stream()
            stream = torch.cuda.Stream()
            self._inputs = tuple(t.clone() for t in inputs)
            stream.wait_stream(current)
            with torch.cuda.stream(stream):
                warm = tuple(fn(*self._inputs))
            current.wait_stream(stream)
            self.first = _copies(warm)
            for t in warm:
                if t is not None and t.is_cuda:
                    # the copies read it on the current stream: its memory must not go back
                    # to the side stream's pool (and the capture's work) before they ran
                    t.record_stream(current)
            del warm
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.stream(stream):
                # "thread_local": other threads' CUDA calls during the capture are theirs
                graph.capture_begin(capture_error_mode="thread_local")
                try:
                    outputs = tuple(fn(*self._inputs))
                except Exception as err:  # noqa: BLE001 - reported through self.error
                    with contextlib.suppress(Exception):
                        graph.capture_end()
                    self.error = err
                    return
                try:
                    graph.capture_end()
                except Exception as err:  # noqa: BLE001 - reported through self.error
                    self.error = err
                    return
            current.wait_stream(stream)
        self._graph, self._outputs = graph, outputs

    def __call__(self, *inputs: Tensor) -> tuple[Tensor | None, ...]:
        if self._graph is None:
            raise RuntimeError(f"the capture failed: {self.error}")
        if len(inputs) != len(self._inputs):
            raise ValueError(f"expected {len(self._inputs)} inputs, got {len(inputs)}")
        for i, (static, t) in enumerate(zip(self._inputs, inputs, strict=True)):
            if t.shape != static.shape or t.dtype != static.dtype or t.device != static.device:
                raise ValueError(
                    f"input {i} must be {static.dtype} {list(static.shape)} on "
                    f"{static.device} (as captured), got {t.dtype} {list(t.shape)} on {t.device}"
                )
            static.copy_(t)
        with torch.cuda.device(self._inputs[0].device):
            self._graph.replay()
        return _copies(self._outputs)
