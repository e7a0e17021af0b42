"""Where the time of a device figure goes: torch.profiler tables of the safety filter on
``B`` states x 8 balls + box, of one MPPI planning call (built-in model and cost terms,
K = 16,384, H = 100), and of the batched QP forward + backward (n = 4, m = 8).

    python scripts/device_profile.py --device cuda --out profile.log

Prints (and writes to ``--out``, table by table) one table per call, sorted by device time
(CPU time on the CPU), after warm-up calls, with the number of kernel launches of one call.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))


def _table(fn: Callable[[], object], device: torch.device, rows: int) -> str:
    for _ in range(2):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    activities = [ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(ProfilerActivity.CUDA)
    with profile(activities=activities) as prof:
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    events = prof.key_averages()
    launches = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cuLaunchKernel"))
    key = "self_cpu_time_total"
    if device.type == "cuda":
        key = (
            "self_device_time_total"
            if hasattr(events[0], "self_device_time_total")
            else ("self_cuda_time_total")
        )
    return f"kernel launches in one call: {launches}\n" + events.table(sort_by=key, row_limit=rows)


def _filter_call(filt: torch.nn.Module, x: torch.Tensor, u_nom: torch.Tensor) -> None:
    with torch.no_grad():
        filt(x, u_nom)


def _mppi_call(planner: torch.nn.Module, x: torch.Tensor) -> None:
    with torch.no_grad():
        planner(x)


def _qp_call(Q: torch.Tensor, p: torch.Tensor, G: torch.Tensor, h: torch.Tensor) -> None:
    from torchcbf.qp import solve_qp

    solve_qp(Q, p.detach().requires_grad_(True), G, h).x.sum().backward()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=("cpu", "cuda"))
    parser.add_argument("--states", type=int, default=1_000_000)
    parser.add_argument("--rows", type=int, default=25)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    device = torch.device(args.device)
    import bench_filters
    import bench_mppi
    import bench_qp

    if args.out is not None:
        args.out.write_text("")

    def emit(title: str, call: Callable[[], object]) -> None:
        # written table by table: a run stopped at its budget keeps the tables it finished
        text = f"## {title}\n\n{_table(call, device, args.rows)}\n"
        sys.stdout.write(text)
        if args.out is not None:
            with args.out.open("a") as fh:
                fh.write(text)

    for dtype in (torch.float32, torch.float64):
        _, _, filt, x, u_nom = bench_filters._scene(args.states, 8, dtype, seed=0)
        call = functools.partial(_filter_call, filt.to(device), x.to(device), u_nom.to(device))
        emit(f"filter, {args.states} states x 8 balls + box, {dtype}", call)
    for graph in (False, True):
        planner = bench_mppi.torchcbf(1, 16384, 100, "builtin", str(device), cuda_graph=graph)
        call = functools.partial(_mppi_call, planner, bench_mppi.x0(0, 4, str(device)))
        title = "MPPI, built-in model and cost terms, K=16384, H=100, float32"
        emit(title + (", cuda_graph=True" if graph else ""), call)
    for dtype in (torch.float32, torch.float64):
        problem = bench_qp.make_problems(args.states, 4, 8, str(device), seed=0)
        call = functools.partial(_qp_call, *(t.to(dtype) for t in problem))
        emit(f"solve_qp forward + backward, B={args.states}, n=4, m=8, {dtype}", call)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
