"""The torch operations (each one kernel launch on a GPU) of one ``SafetyFilter`` call on the
path a GPU takes, and the bytes they read and write, counted on the CPU.

The scene is ``scripts/device_figures.py``'s filter figure (a single integrator among 8
balls, the box as limits). The QP's dual method runs its Triton kernel under Triton's
interpreter (set ``TRITON_INTERPRET=1`` before Python starts; the script makes the dual
method pick that kernel, as it does on CUDA), so the torch operations around it are the
GPU's; the masks a GPU always applies and a CPU skips where no row needs them are not
counted. Bytes are the operations' input and output sizes, scaled to ``--scale`` states:
a model of the memory traffic, not a measurement of it.

    TRITON_INTERPRET=1 python scripts/count_launches.py --dtype float32 --top 15
"""

from __future__ import annotations

import argparse
import collections
import sys
import traceback
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))

#: operations that launch nothing (views, allocations, metadata)
NO_LAUNCH = frozenset(
    "view _unsafe_view expand select slice unsqueeze squeeze t transpose permute as_strided "
    "detach alias _reshape_alias unbind split chunk diagonal lift_fresh empty empty_like "
    "new_empty empty_strided is_nonzero sym_size sym_stride scalar_tensor set_ movedim".split()
)


class _Count(TorchDispatchMode):
    """Each launching operation with the line of torchcbf that called it and its bytes."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: list[tuple[str, str, int]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        frames = [f for f in traceback.extract_stack() if "/torchcbf/" in f.filename]
        where = "?"
        if frames:
            where = f"{frames[-1].filename.split('torchcbf/')[-1]}:{frames[-1].lineno}"
        # the interpreter's own copies of the kernel's arguments launch nothing on a GPU
        if name in NO_LAUNCH or (where.startswith("qp/_dual_triton") and name == "copy_"):
            return out
        tensors = [a for a in args if isinstance(a, torch.Tensor)]
        tensors += [o for o in (out if isinstance(out, (tuple, list)) else [out])]
        size = sum(t.numel() * t.element_size() for t in tensors if isinstance(t, torch.Tensor))
        self.ops.append((name, where, size))
        return out


def count(dtype: torch.dtype, states: int) -> tuple[str, list[tuple[str, str, int]]]:
    """The filter's path and its launching operations on ``states`` states (second call;
    more than :data:`torchcbf.filters.realtime.MAX_BATCH`, or the CPU's real-time path
    answers)."""
    import bench_filters

    from torchcbf.qp import _dual, solve

    def on_cuda(q: torch.Tensor, M: int) -> str:  # the choice on CUDA
        return "triton"

    _dual.dual_engine = solve.dual_engine = on_cuda
    _, _, filt, x, u_nom = bench_filters._scene(states, 8, dtype, seed=0)
    counter = _Count()
    with torch.no_grad():
        filt(x, u_nom)  # the first call's one-time work (caches, compiled kernels) left out
        with counter:
            out = filt(x, u_nom)
    return out.path, counter.ops


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument("--states", type=int, default=2000, help="states traced")
    parser.add_argument("--scale", type=int, default=1_000_000, help="states the bytes are for")
    parser.add_argument("--top", type=int, default=15, help="lines of code listed")
    args = parser.parse_args()
    path, ops = count(getattr(torch, args.dtype), args.states)
    factor = args.scale / args.states
    total = sum(size for _, _, size in ops) * factor
    print(f"path {path}: {len(ops)} launching operations, {total / 1e9:.2f} GB read and written "
          f"at {args.scale} states ({args.dtype})")  # fmt: skip
    by_line: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    for _, where, size in ops:
        by_line[where][0] += 1
        by_line[where][1] += size * factor
    ranked = sorted(by_line.items(), key=lambda kv: -kv[1][1])[: args.top]
    for where, (n, size) in ranked:
        print(f"{size / 1e6:9.1f} MB {n:3d} ops  torchcbf/{where}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
