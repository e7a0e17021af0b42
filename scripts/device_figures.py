"""Headline figures of torchcbf on one device, written as JSON (the measuring half of
``scripts/device_check.sh``).

Each figure is one problem of the benchmark scripts, built with their own helpers
(``bench_mppi``, ``bench_qp``, ``bench_filters``), timed as the median of repeated calls
after warm-up calls, with the device synchronised around every call:

- ``mppi.builtin``: scenario B's planner with the cost built from torchcbf's terms, one
  environment, K = 16,384, H = 100 and K = 20,000, H = 80 (s per planning call), also with
  ``cuda_graph=True`` (``.graph``: the call replayed from a CUDA graph) and on the general
  torch path (``.torch``);
- ``mppi.user``: the same cost written in torch by a user, K = 20,000, H = 80, eager and
  with ``compile=True``; ``mppi.pytorch_mppi``: pytorch-mppi on that problem (skipped, and
  said so, where it is not installed);
- ``qp.fwd_bwd``: ``solve_qp`` forward + backward, n = 4, m = 8, float32 and float64
  (QPs per second, and the share of rows solved);
- ``filter``: ``SafetyFilter`` on a 2-D single integrator with box limits and 8 balls,
  float32 and float64 (s per call, and the share of rows with status 0).

``--quick`` divides every size (a rehearsal that every piece runs, not figures to quote).
A figure that fails is recorded with its error and the exit status is 1; ``--budget``
seconds bound the whole run (figures not started in time are recorded as skipped).

``scripts/device_report.py --collect`` joins this JSON with the test results and the steps
that
``scripts/device_check.sh`` writes.

    python scripts/device_figures.py --device cuda --out figures.json
    python scripts/device_figures.py --device cpu --quick --out figures.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

SCRIPTS = Path(__file__).resolve().parent
if str(SCRIPTS) not in sys.path:  # the bench scripts' problem builders, device_report
    sys.path.insert(0, str(SCRIPTS))

from device_report import strict_json  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(
    fn: Callable[[], object], device: torch.device, *, warmup: int, reps: int, max_seconds: float
) -> dict[str, float]:
    """Median, min and max wall seconds of ``fn`` over ``reps`` calls after ``warmup`` calls
    (fewer repeats, at least 3, where ``max_seconds`` runs out); ``first`` is the first call."""
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    first = time.perf_counter() - t0
    for _ in range(max(warmup - 1, 0)):
        fn()
    _sync(device)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < reps and (len(times) < 3 or time.perf_counter() - start < max_seconds):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return {
        "median": statistics.median(times),
        "min": min(times),
        "max": max(times),
        "reps": len(times),
        "first": first,
    }


class Figures:
    """Collects figures and errors; stops starting new figures once the budget is spent."""

    def __init__(self, budget: float) -> None:
        self.deadline = time.perf_counter() + budget
        self.figures: list[dict[str, Any]] = []
        self.errors: list[dict[str, str]] = []
        self.skipped: list[str] = []

    def run(self, name: str, measure: Callable[[], list[dict[str, Any]]]) -> None:
        if time.perf_counter() > self.deadline:
            self.skipped.append(name)
            print(f"{name:<34} skipped: the time budget is spent", flush=True)
            return
        t0 = time.perf_counter()
        try:
            rows = measure()
        except Exception as err:  # one failing figure must not lose the others
            self.errors.append(
                {
                    "name": name,
                    "error": f"{type(err).__name__}: {err}",
                    "traceback": traceback.format_exc(limit=8),
                }
            )
            print(f"{name:<34} FAILED: {type(err).__name__}: {err}", flush=True)
            return
        for row in rows:
            row.setdefault("seconds_spent", round(time.perf_counter() - t0, 2))
            self.figures.append(row)
            print(
                f"{row['name']:<34} {row['value']:.6g} {row['unit']:<8} {row.get('label', '')}",
                flush=True,
            )


def _mppi(device: torch.device, K: int, H: int, cost: str, reps: int, **kw: Any) -> dict:
    import bench_mppi

    planner = bench_mppi.torchcbf(1, K, H, cost, str(device), **kw)
    x = bench_mppi.x0(0, 4, str(device))
    with torch.no_grad():
        t = _time(lambda: planner(x), device, warmup=2, reps=reps, max_seconds=10.0)
    u = planner(x).u
    if not bool(torch.isfinite(u).all()):
        raise FloatingPointError(f"the planner returned a non-finite control {u.tolist()}")
    return {
        "value": t["median"],
        "unit": "s/call",
        "path": getattr(planner, "path", "torch"),
        "engine": getattr(planner, "engine", None),
        "K": K,
        "H": H,
        "timing": t,
    }


def mppi_figures(device: torch.device, quick: bool, reps: int) -> list[tuple[str, Callable]]:
    scale = 16 if quick else 1

    def builtin(
        K: int, H: int, backend: str = "auto", graph: bool = False
    ) -> Callable[[], list[dict]]:
        def measure() -> list[dict]:
            kw: dict[str, Any] = {"backend": backend, "cuda_graph": graph}
            row = _mppi(device, K // scale, H, "builtin", reps, **kw)
            tag = ("" if backend == "auto" else f".{backend}") + (".graph" if graph else "")
            label = f"MPPI, built-in model and cost terms, K={K // scale}, H={H}"
            if backend != "auto":
                label += f", backend={backend!r} (the general path)"
            if graph:
                label += ", cuda_graph=True"
            row.update(name=f"mppi.builtin{tag}.K{K}.H{H}", label=label)
            return [row]

        return measure

    def user(compiled: bool) -> Callable[[], list[dict]]:
        def measure() -> list[dict]:
            kw = {"compile": True} if compiled else {}
            row = _mppi(device, 20000 // scale, 80, "user", reps, **kw)
            tag = "compiled" if compiled else "eager"
            row.update(
                name=f"mppi.user.{tag}.K20000.H80",
                label=f"MPPI, user torch cost ({tag}), K={20000 // scale}, H=80",
            )
            return [row]

        return measure

    def peer() -> list[dict]:
        import bench_mppi

        K = 20000 // scale
        step = bench_mppi.pytorch_mppi(K, 80, 4, str(device))
        if step is None:
            raise ModuleNotFoundError(
                "pytorch_mppi is not installed (carry it: see the header "
                "of scripts/device_check.sh)"
            )
        x = bench_mppi.x0(0, 4, str(device))
        with torch.no_grad():
            t = _time(lambda: step(x), device, warmup=2, reps=reps, max_seconds=10.0)
        return [
            {
                "name": "mppi.pytorch_mppi.K20000.H80",
                "value": t["median"],
                "unit": "s/call",
                "label": f"pytorch-mppi 0.9.1, same problem and cost, K={K}, H=80",
                "path": "pytorch-mppi",
                "K": K,
                "H": 80,
                "timing": t,
            }
        ]

    return [
        ("mppi.builtin.K16384.H100", builtin(16384, 100)),
        ("mppi.builtin.K20000.H80", builtin(20000, 80)),
        ("mppi.builtin.graph.K16384.H100", builtin(16384, 100, graph=True)),
        ("mppi.builtin.graph.K20000.H80", builtin(20000, 80, graph=True)),
        ("mppi.builtin.torch.K16384.H100", builtin(16384, 100, "torch")),
        ("mppi.user.eager.K20000.H80", user(False)),
        ("mppi.user.compiled.K20000.H80", user(True)),
        ("mppi.pytorch_mppi.K20000.H80", peer),
    ]


def qp_figure(device: torch.device, dtype: torch.dtype, B: int, reps: int) -> Callable:
    def measure() -> list[dict]:
        import bench_qp

        from torchcbf.qp import solve_qp

        Q, p, G, h = (t.to(dtype) for t in bench_qp.make_problems(B, 4, 8, str(device), seed=0))
        status: list[torch.Tensor] = []
        paths: list[str] = []

        def fwd_bwd() -> None:
            pr = p.detach().requires_grad_(True)
            hr = h.detach().requires_grad_(True)
            sol = solve_qp(Q, pr, G, hr)
            sol.x.sum().backward()
            status[:] = [sol.status]
            paths[:] = [sol.path]

        t = _time(fwd_bwd, device, warmup=1, reps=reps, max_seconds=10.0)
        solved = float((status[0] == 0).double().mean())
        name = {torch.float32: "float32", torch.float64: "float64"}[dtype]
        return [
            {
                "name": f"qp.fwd_bwd.n4.m8.{name}",
                "value": B / t["median"],
                "unit": "QP/s",
                "label": f"solve_qp forward+backward, B={B}, n=4, m=8, {name}",
                "B": B,
                "solved_fraction": solved,
                "path": paths[0],
                "timing": t,
            }
        ]

    return measure


def filter_figure(device: torch.device, dtype: torch.dtype, B: int, reps: int) -> Callable:
    def measure() -> list[dict]:
        import bench_filters

        dyn, ball, filt, x, u_nom = bench_filters._scene(B, 8, dtype, seed=0)
        filt = filt.to(device)
        x, u_nom = x.to(device), u_nom.to(device)
        outs: list[Any] = []

        def call() -> None:
            outs[:] = [filt(x, u_nom)]

        with torch.no_grad():
            t = _time(call, device, warmup=2, reps=reps, max_seconds=10.0)
        ok = float((outs[0].status == 0).double().mean())
        name = {torch.float32: "float32", torch.float64: "float64"}[dtype]
        return [
            {
                "name": f"filter.balls8_box.{name}",
                "value": t["median"],
                "unit": "s/call",
                "label": f"SafetyFilter, {B} states x 8 balls + box, {name}",
                "B": B,
                "status0_fraction": ok,
                "path": outs[0].path,
                "timing": t,
            }
        ]

    return measure


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args],
            capture_output=True,
            text=True,
            cwd=SCRIPTS.parent,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def provenance(device: torch.device) -> dict[str, Any]:
    """Card, software and commit. The commit comes from ``build/device-carry/commit.txt``
    where it exists (written by ``device_check.sh --prepare`` for the tree that travels to
    the device, which may sit inside another checkout), else from git."""
    commit, dirty = None, None
    stamp = SCRIPTS.parent / "build" / "device-carry" / "commit.txt"
    if stamp.is_file():
        fields = stamp.read_text().split()
        commit = fields[0] if fields else None
        dirty = len(fields) > 1 and fields[1] == "dirty"
    else:
        commit = _git("rev-parse", "HEAD")
        if commit:
            dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
    if device.type == "cuda":
        card = torch.cuda.get_device_name(device)
        props = torch.cuda.get_device_properties(device)
        memory = round(props.total_memory / 2**30, 1)
    else:
        card = platform.processor() or platform.machine()
        memory = None
    try:
        import triton

        triton_version = triton.__version__
    except ImportError:
        triton_version = None
    return {
        "device": device.type,
        "card": card,
        "card_memory_gib": memory,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "commit": commit,
        "dirty": dirty,
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "triton": triton_version,
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "load_average": os.getloadavg()[0],
    }


def measure(args: argparse.Namespace) -> int:
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("device_figures: --device cuda, but torch sees no GPU", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    import torchcbf  # noqa: F401  (fail here, loudly, if the package does not import)

    reps = 3 if args.quick else args.reps
    big = 10_000 if args.quick else 1_000_000
    plan = mppi_figures(device, args.quick, reps)
    for dtype in (torch.float32, torch.float64):
        name = "float32" if dtype == torch.float32 else "float64"
        plan.append((f"qp.fwd_bwd.n4.m8.{name}", qp_figure(device, dtype, big, reps)))
        plan.append((f"filter.balls8_box.{name}", filter_figure(device, dtype, big, reps)))
    if args.only:
        plan = [(n, m) for n, m in plan if any(n.startswith(o) for o in args.only)]
    figs = Figures(args.budget)
    info = provenance(device)
    print(f"{info['card']} ({info['device']}), torch {info['torch']}, commit {info['commit']}")

    def write() -> None:  # after every figure: a run stopped from outside keeps what it has
        result = {
            **info,
            "quick": args.quick,
            "figures": figs.figures,
            "errors": figs.errors,
            "skipped": figs.skipped,
        }
        Path(args.out).write_text(json.dumps(strict_json(result), indent=1))

    write()
    for name, fn in plan:
        figs.run(name, fn)
        write()
    print(
        f"wrote {args.out}: {len(figs.figures)} figures, {len(figs.errors)} errors, "
        f"{len(figs.skipped)} skipped"
    )
    return 1 if figs.errors or figs.skipped else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    parser.add_argument("--quick", action="store_true", help="sizes divided (a rehearsal)")
    parser.add_argument("--reps", type=int, default=10, help="timed calls per figure")
    parser.add_argument("--budget", type=float, default=200.0, help="seconds for all figures")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (CPU work)")
    parser.add_argument("--only", nargs="+", help="figure name prefixes to run")
    parser.add_argument("--out", default="figures.json", help="JSON file written")
    args = parser.parse_args()
    return measure(args)


if __name__ == "__main__":
    sys.exit(main())
