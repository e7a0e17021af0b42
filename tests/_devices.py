"""Devices for the tests: which ones a run uses (``TORCHCBF_TEST_DEVICES``), and the
comparison of a device's answers with the CPU's.

A module of its own (not conftest.py) so that a test imports it by a name no other folder's
conftest shadows: ``from _devices import device_matches_cpu``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import torch

from torchcbf._triton import available as triton_available
from torchcbf._triton import interpreted as triton_interpreted


def _present(name: str) -> bool:
    if name == "cpu":
        return True
    if name == "cuda":
        return torch.cuda.is_available()
    return False


def devices() -> list[str]:
    """The device fixture's devices: ``TORCHCBF_TEST_DEVICES`` (comma-separated) where set,
    else the CPU and CUDA where present; a named device that is absent is a usage error."""
    chosen = os.environ.get("TORCHCBF_TEST_DEVICES", "").strip()
    if not chosen:
        return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    names = [name.strip() for name in chosen.split(",") if name.strip()]
    missing = [name for name in names if not _present(name)]
    if missing:
        raise pytest.UsageError(
            f"TORCHCBF_TEST_DEVICES={chosen!r}: {missing} not present here "
            f"(cuda available: {torch.cuda.is_available()}); known devices: cpu, cuda"
        )
    return list(dict.fromkeys(names))


#: how far a device's answer may be from the CPU's, by dtype: (rtol, atol)
DEVICE_TOL = {torch.float64: (1e-9, 1e-9), torch.float32: (1e-4, 1e-5)}


def _leaves(out: Any, path: str = "out") -> Iterator[tuple[str, Any]]:
    if isinstance(out, torch.Tensor) or out is None or isinstance(out, str | int | float | bool):
        yield path, out
    elif isinstance(out, dict):
        for key, value in out.items():
            yield from _leaves(value, f"{path}[{key!r}]")
    elif isinstance(out, tuple | list):
        names = getattr(out, "_fields", None) or range(len(out))
        for name, value in zip(names, out, strict=True):
            yield from _leaves(value, f"{path}.{name}")
    else:
        raise TypeError(f"device_matches_cpu: cannot compare {path} of type {type(out).__name__}")


def assert_same_answers(
    got: Any,
    want: Any,
    dtype: torch.dtype = torch.float64,
    *,
    where: str = "device",
    rtol: float | None = None,
    atol: float | None = None,
) -> None:
    """``got`` (any device) equals ``want`` (CPU) leaf by leaf: floating tensors to
    ``DEVICE_TOL[dtype]`` (or ``rtol``/``atol``), other tensors and leaves exactly."""
    d_rtol, d_atol = DEVICE_TOL[dtype]
    for (path, a), (_, b) in zip(_leaves(got), _leaves(want), strict=True):
        if isinstance(b, torch.Tensor):
            assert isinstance(a, torch.Tensor), f"{path}: {type(a).__name__}, not a tensor"
            exact = not (b.is_floating_point() or b.is_complex())
            torch.testing.assert_close(
                a.cpu(), b, rtol=0 if exact else (rtol if rtol is not None else d_rtol),
                atol=0 if exact else (atol if atol is not None else d_atol), equal_nan=True,
                msg=lambda m, path=path: f"{path} on {where} differs from the CPU's: {m}",
            )  # fmt: skip
        else:
            assert a == b, f"{path}: {a!r} on {where}, {b!r} on the CPU"


def device_matches_cpu(
    fn: Callable[[torch.device], Any],
    device: torch.device,
    dtype: torch.dtype = torch.float64,
    *,
    rtol: float | None = None,
    atol: float | None = None,
) -> Any:
    """``fn(device)``, checked against ``fn(cpu)`` where ``device`` is not the CPU.

    ``fn`` builds its inputs and modules on the device it is given (the same values on every
    device: draw them on the CPU, then move them) and returns a tensor or a (named) tuple,
    list or dict of them (other leaves: numbers, strings, None). Every tensor of the device
    run lives on ``device``; floating tensors agree with the CPU run to ``DEVICE_TOL[dtype]``
    (or ``rtol``/``atol``), the others exactly. Returns the device run's result."""
    device = torch.device(device)
    out = fn(device)
    for path, value in _leaves(out):
        if isinstance(value, torch.Tensor):
            assert value.device.type == device.type, f"{path} is on {value.device}, not {device}"
    if device.type == "cpu":
        return out
    ref = fn(torch.device("cpu"))
    assert_same_answers(out, ref, dtype, where=str(device), rtol=rtol, atol=atol)
    return out


def triton_target() -> torch.device | None:
    """Where the Triton kernels' tests run: CUDA where present, else the CPU in Triton's
    interpreter (``TRITON_INTERPRET=1`` set before Python starts), else nowhere."""
    if torch.cuda.is_available():
        return torch.device("cuda", torch.cuda.current_device())  # equal to a tensor's device
    return torch.device("cpu") if triton_interpreted() else None


#: marks of a Triton kernel's tests: Triton imports, and a device runs the kernel
NEEDS_TRITON = pytest.mark.skipif(not triton_available(), reason="Triton is not installed")
RUNS_TRITON = pytest.mark.skipif(
    triton_target() is None, reason="no CUDA device and TRITON_INTERPRET is not 1"
)
