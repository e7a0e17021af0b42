"""Shared fixtures: every numerical test runs over dtypes x devices.

Devices. ``DEVICES`` is ``["cpu"]``, plus ``"cuda"`` where torch sees a GPU; a test that takes
the ``device`` fixture runs once per entry. The environment variable
``TORCHCBF_TEST_DEVICES`` (comma-separated, e.g. ``cuda`` or ``cpu,cuda``) chooses the entries
instead; naming a device that is not present is a usage error, not a silent skip. Every test
that takes the fixture, and every test with ``cuda`` in its name, carries the ``device``
marker, so ``TORCHCBF_TEST_DEVICES=cuda pytest -m "device and not slow"`` runs exactly the
tests that exercise CUDA (``scripts/device_check.sh`` does this on a GPU machine).
``_devices.device_matches_cpu`` runs a computation on the fixture's device and on the CPU
and compares the two (float64 to 1e-9, float32 to 1e-4); on the CPU it runs once.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
import torch
from _devices import devices

DEVICES = devices()
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
