"""torchcbf._native: the heap settings that keep a sliced torch cost from page-faulting."""

from __future__ import annotations

import ctypes
import logging
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from torchcbf._native import keep_freed_heap, load_kernel, prototypes

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


_SOURCE = """
static int helper(int n) { return n; }
int torchcbf_demo_version(void) { return 3; }
int torchcbf_demo_solve(int64_t B, int m, const double *x, double eps,
                        lie_kernel fn, void *const *ptrs) {
    return 0;
}
double torchcbf_demo_norm(int n, const float *v) { return 0.0; }
int SUFFIX(torchcbf_demo_fill)(const REAL *a, REAL scale, uint64_t key) { return 0; }
"""


def test_prototypes_read_every_exported_definition(tmp_path: Path) -> None:
    src = tmp_path / "demo.c"
    src.write_text(_SOURCE)
    found = prototypes([src])
    P, D, F, I64 = ctypes.c_void_p, ctypes.c_double, ctypes.c_float, ctypes.c_int64
    assert found == {
        "torchcbf_demo_version": ([], ctypes.c_int),
        "torchcbf_demo_solve": ([I64, ctypes.c_int, P, D, P, P], ctypes.c_int),
        "torchcbf_demo_norm": ([ctypes.c_int, P], D),
        "torchcbf_demo_fill_f32": ([P, F, ctypes.c_uint64], ctypes.c_int),
        "torchcbf_demo_fill_f64": ([P, D, ctypes.c_uint64], ctypes.c_int),
    }


@pytest.mark.parametrize(
    ("module", "attribute"),
    [
        ("torchcbf.filters.realtime", "_library"),
        ("torchcbf.mppi._rollout", "_library"),
        ("torchcbf.barriers.native", "_library"),
    ],
)
def test_each_built_kernel_has_its_sources_interface(module: str, attribute: str) -> None:
    import importlib

    lib = getattr(importlib.import_module(module), attribute)()
    if lib is None:
        pytest.skip("the kernel was not built")
    directory = Path(lib._name).parent
    sources = sorted(directory.glob("_*_kernel.[ch]"))
    for name, (argtypes, restype) in prototypes(sources).items():
        function = getattr(lib, name)
        assert function.argtypes == argtypes and function.restype is restype, name


def test_a_kernel_whose_source_cannot_be_read_is_refused(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from torchcbf.barriers import native

    lib = native._library()
    if lib is None:
        pytest.skip("the kernel was not built")
    built = Path(lib._name)
    (tmp_path / built.name).symlink_to(built)
    with caplog.at_level(logging.WARNING, logger="torchcbf"):
        got = load_kernel(
            tmp_path, "_lie_kernel", "torchcbf_lie_version", native.KERNEL_VERSION, "torch",
            sources=("_lie_kernel.c",),
        )  # fmt: skip
    assert got is None and "cannot read the interface" in caplog.text
