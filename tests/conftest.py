"""Shared fixtures: every numerical test runs over dtypes x devices.

Devices. ``DEVICES`` is ``["cpu"]``, plus ``"cuda"`` where torch sees a GPU; a test that takes
the ``device`` fixture runs once per entry. The environment variable
``TORCHCBF_TEST_DEVICES`` (comma-separated, e.g. ``cuda`` or ``cpu,cuda``) chooses the entries
instead; naming a device that is not present is a usage error, not a silent skip. Every test
that takes the fixture, and every test with ``cuda`` in its name, carries the ``device``
marker, so ``TORCHCBF_TEST_DEVICES=cuda pytest -m "device and not slow"`` runs exactly the
tests that exercise CUDA (``scripts/device_check.sh`` does this on a GPU machine).
:func:`device_matches_cpu` runs a computation on the fixture's device and on the CPU and
compares the two (float64 to 1e-9, float32 to 1e-4); on the CPU it runs once.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import torch


def _present(name: str) -> bool:
    if name == "cpu":
        return True
    if name == "cuda":
        return torch.cuda.is_available()
    return False


def _devices() -> list[str]:
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


DEVICES = _devices()
DTYPES = [torch.float64, torch.float32]


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float64", "float32"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param


def tol(dtype: torch.dtype, f64: float = 1e-10, f32: float = 1e-4) -> float:
    """A tolerance chosen by dtype."""
    return f64 if dtype == torch.float64 else f32


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


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """One intra-op thread per test: the batches here are small, and a second OpenMP thread on
    a 2-core CI machine only adds barrier waits (measured up to 1000x slower under load)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "device: the test takes the device fixture or names cuda (set automatically; select "
        "with -m device, and the devices with TORCHCBF_TEST_DEVICES)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``slow`` reproductions run only when selected (``-m slow``) or with ``TORCHCBF_SLOW=1``,
    so a plain ``pytest`` stays fast. Tests on a device get the ``device`` marker."""
    for item in items:
        if "device" in getattr(item, "fixturenames", ()) or "cuda" in item.name.lower():
            item.add_marker(pytest.mark.device)
    markexpr = config.getoption("-m") or ""
    if os.environ.get("TORCHCBF_SLOW") == "1" or (
        "slow" in markexpr and "not slow" not in markexpr
    ):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow or TORCHCBF_SLOW=1")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
