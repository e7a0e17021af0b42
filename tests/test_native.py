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

from torchcbf._native import constants, keep_freed_heap, load_kernel, prototypes

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


@pytest.mark.slow
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
int torchcbf_demo_declared(int n);
int torchcbf_demo_solve(int64_t B /* rows */, int m, // controls
                        const double *x, double eps,
                        lie_kernel fn, void *const *ptrs, const double w[3]) /* c */ {
    return 0;
}
double torchcbf_demo_norm(int n, const float *v) { return 0.0; }
void torchcbf_demo_clear(size_t n, double *v) { }
int SUFFIX(torchcbf_demo_fill)(const REAL *a, REAL scale, uint64_t key) { return 0; }
"""


def test_prototypes_read_every_exported_definition(tmp_path: Path) -> None:
    src = tmp_path / "demo.c"
    src.write_text(_SOURCE)
    found = prototypes([src])
    P, D, F, I64 = ctypes.c_void_p, ctypes.c_double, ctypes.c_float, ctypes.c_int64
    assert found == {
        "torchcbf_demo_version": ([], ctypes.c_int),
        "torchcbf_demo_solve": ([I64, ctypes.c_int, P, D, P, P, P], ctypes.c_int),
        "torchcbf_demo_norm": ([ctypes.c_int, P], D),
        "torchcbf_demo_clear": ([ctypes.c_size_t, P], None),
        "torchcbf_demo_fill_f32": ([P, F, ctypes.c_uint64], ctypes.c_int),
        "torchcbf_demo_fill_f64": ([P, D, ctypes.c_uint64], ctypes.c_int),
    }
    src.write_text("int torchcbf_demo_odd(unsigned short n) { return 0; }\n")
    with pytest.raises(ValueError, match="unsigned short"):
        prototypes([src])


def test_constants_read_defines_and_enums(tmp_path: Path) -> None:
    src = tmp_path / "demo.c"
    src.write_text(
        "#define WIDTH 4  /* lanes */\n"
        "#define NAME_ONLY\n"
        "enum { A, B, C = 7, D };  // D = 8\n"
        "#define OCTAL 010\n"
        "enum named { E = D + 2 };\n"
        "/* enum { HIDDEN = 99 }; */\n"
        "enum { F_HEAD, F_IDX, F_CENTER = F_IDX + WIDTH, F_AXES = F_CENTER + 2 * WIDTH,\n"
        "       F_SIZE = 20 };\n"
    )
    assert constants([src]) == {
        "WIDTH": 4, "A": 0, "B": 1, "C": 7, "D": 8, "E": 10,
        "F_HEAD": 0, "F_IDX": 1, "F_CENTER": 5, "F_AXES": 13, "F_SIZE": 20,
    }  # fmt: skip
    src.write_text("enum { BAD = sizeof(double) };\n")
    with pytest.raises(ValueError, match="sizeof"):
        constants([src])


def test_the_rollout_configuration_fields_are_the_c_sources() -> None:
    from torchcbf.mppi import _rollout

    layout = _rollout.LAYOUT
    terms = [layout[n] for n in ("TR_TYPE", "TR_D", "TR_IDX", "TR_CENTER", "TR_RADIUS")]
    shapes = [layout[n] for n in ("SR_KIND", "SR_IDX", "SR_CENTER", "SR_AXES", "SR_ANGLE")]
    assert max(terms) < layout["TREC"] and max(shapes) < layout["SREC"]
    assert layout["TR_CENTER"] - layout["TR_IDX"] == layout["DMAX"] == _rollout.MAX_DIM
    rec = _rollout.record("SREC", SR_D=2, SR_IDX=[0, 1], SR_ANGLE=0.5)
    assert _rollout.field(rec, "SR_IDX", 2) == [0.0, 1.0] and _rollout.field(rec, "SR_ANGLE") == 0.5
    assert len(rec) == layout["SREC"] and sum(rec) == 3.5
    with pytest.raises(ValueError, match="SR_IDX"):
        _rollout.record("SREC", SR_IDX=list(range(layout["DMAX"] + 1)))
    with pytest.raises(ValueError, match="TR_NSHAPE"):
        _rollout.record("TREC", TR_NSHAPE=[1, 2, 3])


def test_every_exported_symbol_has_its_sources_types() -> None:
    """Every ``torchcbf_*`` function a built library exports (``nm -D``) is read from the
    sources beside it, with the types the library's functions were given."""
    import importlib
    import shutil

    if shutil.which("nm") is None:
        pytest.skip("nm is not installed")
    for module in ("torchcbf.qp._dual_native", "torchcbf.barriers.native",
                   "torchcbf.mppi._rollout"):  # fmt: skip
        lib = importlib.import_module(module)._library()
        if lib is None:
            continue
        path = Path(lib._name)
        listed = subprocess.run(
            ["nm", "-D", "--defined-only", str(path)], capture_output=True, text=True, check=True
        ).stdout.split()
        exported = {name for name in listed if name.startswith("torchcbf_")}
        found = prototypes(sorted(path.parent.glob("_*_kernel.[ch]")))
        assert exported == set(found), module
        for name, (argtypes, restype) in found.items():
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


def test_a_packer_places_values_by_name() -> None:
    from torchcbf.barriers import native

    layout = native.LAYOUT
    pack = layout.packer("G_FIXED", "G_OUTPUTS", "G_MODE")  # any order, missing slots 0
    rec = pack(7, 2)
    assert len(rec) == layout["G_FIXED"] and sum(rec) == 9
    assert rec[layout["G_OUTPUTS"]] == 7 and rec[layout["G_MODE"]] == 2
    assert rec == layout.record("G_FIXED", cast=int, G_OUTPUTS=7, G_MODE=2)
    with pytest.raises(ValueError, match="M_INNER"):
        layout.packer("G_FIXED", "M_INNER")  # past this record's slots
