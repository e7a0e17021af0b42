"""Fixtures for the estimation tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread() -> Iterator[None]:
    """One intra-op thread: the filters' kernels are small batched matrix exponentials and
    Cholesky factors that get much slower with an OpenMP team on a loaded 2-core machine
    (measured here: 11 min with 2 threads under load vs 27 s with one)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
