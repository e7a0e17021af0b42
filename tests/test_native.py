"""torchcbf._native: the heap settings that keep a sliced torch cost from page-faulting."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from torchcbf._native import keep_freed_heap

CHURN = """
import resource, sys, torch
from torchcbf._native import keep_freed_heap
if sys.argv[1] == "keep":
    assert keep_freed_heap() and keep_freed_heap()
def churn():
    parts = [torch.ones(800_000) for _ in range(5)]  # five 3.2 MB blocks, then all freed
    del parts
churn()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(30):
    churn()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str, **malloc: str) -> int:
    # without the environment's own malloc settings, if any, and with ``malloc``'s
    env = {
        k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"
    }
    env.update(malloc)
    out = subprocess.run(
        [sys.executable, "-c", CHURN, mode], capture_output=True, text=True, check=True, env=env
    )
    return int(out.stdout.strip())


@pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only"
)
def test_freed_blocks_are_reused_without_page_faults():
    # A heap that hands such blocks back maps them again every round, 780 pages apiece.
    # Whether glibc's defaults do depends on what the process freed before (its thresholds
    # are dynamic: the imports of one environment gave 93,506 faults here, of another
    # 4,584), so that heap is pinned with glibc's initial threshold, which also turns the
    # adjustment off; keep_freed_heap must hold whatever came before.
    assert _faults("default", MALLOC_MMAP_THRESHOLD_="131072") > 30 * 780
    assert _faults("keep") < 5 * 780


def test_keep_freed_heap_is_once_per_process():
    first = keep_freed_heap()
    assert keep_freed_heap() is first
    assert keep_freed_heap.cache_info().hits >= 1
