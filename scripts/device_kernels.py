"""Launch settings of the QP's Triton kernel (:mod:`torchcbf.qp._dual_triton`), timed on the
device: problems per program, warps per program and a cap on registers per thread.

The problem is the safety filter's QP of ``scripts/device_profile.py`` (``--states`` states
of a single integrator among 8 balls, controls boxed in [-2, 2], a slack: 3 variables and
13 rows with the box as rows), in float32 and float64. Each setting is timed (median of
``--reps`` launches after a first one that compiles, synchronised around each) and its
answers are compared with the first setting's (the default, unless ``--settings`` says
otherwise: rows solved, largest difference of ``x``).
A program of fewer problems than threads splits each problem's tiles over several threads
(fewer registers per thread, reductions across threads); a register cap trades registers
for spills and more resident warps. The first setting is timed once more with the inputs
copied into planes with the batch last before the launch (layout ``planes``; the kernel
reads the inputs at their own strides otherwise).

    python scripts/device_kernels.py --device cuda --out kernels.json
    TRITON_INTERPRET=1 python scripts/device_kernels.py --device cpu --states 64 --reps 1

Prints one line per setting as it finishes (and rewrites ``--out``, a JSON list, after each),
so a run stopped at its time limit keeps what it measured. The registers and spills are
read from the compiled kernel where Triton reports them (not under its interpreter).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))

#: (problems per program, warps, register cap): the default first, then by expected value
SETTINGS: tuple[tuple[int, int, int | None], ...] = (
    (32, 1, None),
    (16, 1, None),
    (8, 1, None),
    (32, 2, None),
    (32, 4, None),
    (32, 1, 128),
    (64, 2, None),
)

#: the smallest batch whose QP is captured from the filter
CAPTURED = 4096


def filter_qp(states: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
    """``P [B, 3, 3], q [B, 3], G [B, 13, 3], h [B, 13]``: the filter's QP on ``states``
    states with its box bounds written as rows (captured from a batch of at least
    :data:`CAPTURED` states: a smaller one takes the filter's one-call C path on the CPU)."""
    import bench_filters

    _, _, filt, x, u_nom = bench_filters._scene(max(states, CAPTURED), 8, dtype, seed=0)
    captured = bench_filters._capture_qp(filt, x, u_nom)
    if captured is None:
        raise RuntimeError("the filter answered without solve_qp: no QP to time")
    args, kw = captured
    P, q, G, h = (t[:states] for t in args[:4])
    kw = {k: v[:states] if isinstance(v, torch.Tensor) else v for k, v in kw.items()}
    B, _, n = G.shape
    eye = torch.eye(n, dtype=dtype).expand(B, n, n)
    rows, rhs = [G], [h]
    for i in range(n):
        for sign, bound in ((1.0, kw.get("ub")), (-1.0, kw.get("lb"))):
            if bound is not None and bool(torch.isfinite(bound[:, i]).all()):
                rows.append(sign * eye[:, i : i + 1])
                rhs.append(sign * bound[:, i : i + 1])
    return tuple(t.contiguous().to(device) for t in (P, q, torch.cat(rows, 1), torch.cat(rhs, 1)))


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(
    problem: tuple[torch.Tensor, ...],
    setting: tuple[int, int, int | None],
    reps: int,
    *,
    planes: bool = False,
) -> tuple[dict, object]:
    """One setting on one problem: the first call's seconds, the median of ``reps`` more in
    ms, and the registers and spills of the variant the first call compiled; ``planes``: the
    inputs copied into planes with the batch last first (the copies timed with the kernel)."""
    from torchcbf.qp import _dual_triton

    block, warps, maxnreg = setting
    device = problem[0].device
    eps = 1e-6 if problem[0].dtype == torch.float32 else 1e-9

    def call() -> _dual_triton.Solution:
        return _dual_triton.solve(
            *problem, eps=eps, max_iter=50, block=block, warps=warps, maxnreg=maxnreg,
            planes=planes,
        )  # fmt: skip

    before = _compiled(device)
    _synchronize(device)
    t = time.perf_counter()
    sol = call()
    _synchronize(device)
    first = time.perf_counter() - t
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        call()
        _synchronize(device)
        times.append(time.perf_counter() - t)
    row = {"block": block, "warps": warps, "maxnreg": maxnreg, "first_s": first}
    row["layout"] = "planes" if planes else "strides"
    row["median_ms"] = 1e3 * statistics.median(times) if times else None
    new = [k for k in _compiled(device) if all(k is not b for b in before)]
    if len(new) == 1:  # a setting seen before in this process reuses its variant: not read
        row.update(_resources(new[0]))
    return row, sol


def _compiled(device: torch.device) -> list:
    """The QP kernel's compiled variants in Triton's in-memory cache for ``device`` (none on
    the CPU, where the interpreter compiles nothing)."""
    from torchcbf.qp import _dual_triton

    caches = getattr(_dual_triton._dual_solve_kernel, "device_caches", None)
    if device.type != "cuda" or not caches:
        return []
    try:
        return list(caches[torch.cuda.current_device()][0].values())
    except (IndexError, KeyError, TypeError):
        return []


def _resources(compiled: object) -> dict:
    """Registers and spills of one compiled variant (empty where Triton does not say)."""
    try:
        compiled._init_handles()
        return {"regs": int(compiled.n_regs), "spills": int(compiled.n_spills)}
    except (AttributeError, RuntimeError, TypeError, ValueError):
        return {}


def parse_settings(names: list[str] | None) -> tuple[tuple[int, int, int | None], ...]:
    """Settings from ``BLOCKxWARPS`` or ``BLOCKxWARPSxMAXNREG`` names (``None``: all of
    :data:`SETTINGS`)."""
    if not names:
        return SETTINGS
    parsed = [tuple(int(v) for v in name.split("x")) for name in names]
    return tuple((p[0], p[1], p[2] if len(p) > 2 else None) for p in parsed)


def _name(setting: tuple[int, int, int | None]) -> str:
    return "x".join(str(v) for v in setting if v is not None)


def compile_all(
    device: str,
    dtypes: list[str],
    settings: tuple[tuple[int, int, int | None], ...],
    jobs: int,
    deadline: float = 90.0,
) -> None:
    """Compile each (dtype, setting) in a process of its own, ``jobs`` at a time, within
    ``deadline`` seconds (then the rest are stopped): one call on 32 states, which Triton
    compiles as a call on 10^6 (the kernel leaves the batch size unspecialised), so its disk
    cache holds the kernels the timed runs launch. Prints what failed or was stopped."""
    started = time.perf_counter()
    todo = [(d, s) for d in dtypes for s in settings]
    running: list[tuple[subprocess.Popen, str]] = []
    failed: list[str] = []
    while todo or running:
        while todo and len(running) < jobs:
            dtype, setting = todo.pop(0)
            cmd = [sys.executable, __file__, "--device", device, "--states", "32", "--reps", "0"]
            cmd += ["--dtypes", dtype, "--settings", _name(setting)]
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            running.append((proc, f"{dtype} {_name(setting)}"))
        time.sleep(0.2)
        late = time.perf_counter() - started > deadline
        for proc, name in list(running):
            if late and proc.poll() is None:
                proc.kill()
                proc.wait()
                failed.append(f"{name} (stopped at {deadline:.0f} s)")
            elif proc.poll() is not None and proc.returncode != 0:
                failed.append(f"{name} (exit {proc.returncode})")
            if proc.poll() is not None:
                running.remove((proc, name))
        if late:
            failed += [f"{d} {_name(s)} (not started)" for d, s in todo]
            todo = []
    count = len(dtypes) * len(settings)
    note = f"; failed: {', '.join(failed)}" if failed else ""
    elapsed = time.perf_counter() - started
    print(
        f"compiled {count - len(failed)} of {count} settings in {jobs} processes "
        f"({elapsed:.1f} s){note}",
        flush=True,
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=("cpu", "cuda"))
    parser.add_argument("--states", type=int, default=1_000_000)
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    parser.add_argument(
        "--settings",
        nargs="+",
        help="BLOCKxWARPS or BLOCKxWARPSxMAXNREG (default: all of SETTINGS)",
    )
    parser.add_argument(
        "--compile-jobs",
        type=int,
        default=0,
        help="compile every setting first in this many processes at once (Triton's disk "
        "cache then serves the timed runs; 0: compile in the first call of each)",
    )
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    device = torch.device(args.device)
    settings = parse_settings(args.settings)
    if args.compile_jobs > 0:
        compile_all(args.device, args.dtypes, settings, args.compile_jobs)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    results: list[dict] = []
    print(f"{name}: the filter's QP, {args.states} states, 3 variables, 13 rows")
    for dtype_name in args.dtypes:
        dtype = getattr(torch, dtype_name)
        problem = filter_qp(args.states, dtype, device)
        reference = None
        # every setting on the inputs as given, then the first on inputs copied into planes
        runs = [(s, False) for s in settings] + [(settings[0], True)]
        for setting, planes in runs:
            row, sol = measure(problem, setting, args.reps, planes=planes)
            if reference is None:
                reference = sol
            both = reference.ok & sol.ok
            dx = (reference.x - sol.x).abs().amax(0)[both]
            row.update(
                card=name,
                dtype=dtype_name,
                states=args.states,
                solved=int(sol.ok.sum()),
                solved_default=int(reference.ok.sum()),
                max_dx=float(dx.max()) if dx.numel() else 0.0,
            )
            results.append(row)
            median = "-" if row["median_ms"] is None else f"{row['median_ms']:.3f} ms"
            print(
                f"{dtype_name} block={row['block']} warps={row['warps']} "
                f"maxnreg={row['maxnreg']} {row['layout']}: {median} "
                f"(first {row['first_s']:.1f} s), "
                f"regs {row.get('regs', '-')}, spills {row.get('spills', '-')}, solved "
                f"{row['solved']}/{args.states} (default {row['solved_default']}), "
                f"max |dx| {row['max_dx']:.2e}",
                flush=True,
            )
            if args.out is not None:
                args.out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
