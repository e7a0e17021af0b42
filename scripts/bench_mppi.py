"""Benchmark: time per MPPI planning step, torchcbf (eager, compiled) vs pytorch-mppi 0.9.1.

Problem (SCENARIOS.md B): AccelUnicycle (x, y, v, theta; a, omega), Euler rollouts with
dt = 0.02, float32; stage cost ``2 |p - goal|^2 + sum_i 2 / max(b_i, 0.01)`` over the five
ellipses, terminal ``10 |p - goal|^2``; temperature 0.03; control-cost weight 0.1
(pytorch-mppi has no separate control-cost weight: its ``lambda_`` = 0.03 plays both roles).
The scenario leaves the sampling covariance open: both planners use ``noise_sigma = I`` and
no control limits. The planning state is x0 = (0, 0, 0, pi/4) with the plan warm-started
(each timed step is a full planning call: sampling, rollouts, costs, weights, update).

Usage::

    python scripts/bench_mppi.py            # (K, H) in (1000, 50), (10000, 50), (20000, 80)
    python scripts/bench_mppi.py --quick    # (1000, 50) only, fewer repeats
    python scripts/bench_mppi.py --threads 1 --device cuda

Each (planner, K, H) runs in its own subprocess so that peak memory is per planner.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from collections.abc import Callable

import torch

from torchcbf.dynamics import AccelUnicycle
from torchcbf.mppi import MPPI, BarrierCost, QuadraticGoal, SumCost

GOAL = (2.0, 4.0)
ELLIPSES = (  # centre, semi-axes (SCENARIOS.md B)
    ((1.0, 2.0), (0.5, 1.5)),
    ((3.0, 2.0), (0.75, 2.0)),
    ((2.0, 5.0), (2.0, 0.25)),
    ((-1.0, 1.0), (1.0, 0.75)),
    ((0.5, -1.0), (0.75, 0.5)),
)
DT, TEMPERATURE, GAMMA = 0.02, 0.03, 0.1


class _Ellipse(torch.nn.Module):
    """``((x - xo)/a1)^2 + ((y - yo)/a2)^2 - 1`` (local helper, not the barriers package)."""

    def __init__(self, center: tuple[float, float], axes: tuple[float, float]) -> None:
        super().__init__()
        self.cx, self.cy = center
        self.ix, self.iy = 1.0 / axes[0], 1.0 / axes[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        dx = (x[..., 0] - self.cx) * self.ix
        dy = (x[..., 1] - self.cy) * self.iy
        return dx * dx + dy * dy - 1.0


def torchcbf_cost() -> SumCost:
    goal = QuadraticGoal(GOAL, weight=2.0, index=(0, 1), terminal_weight=10.0)
    return SumCost(goal, *(BarrierCost(_Ellipse(c, a), 2.0, 0.01) for c, a in ELLIPSES))


def make_torchcbf(K: int, H: int, compile: bool, device: str) -> Callable[[torch.Tensor], object]:
    planner = MPPI(
        AccelUnicycle(),
        torchcbf_cost(),
        H,
        K,
        DT,
        torch.eye(2),
        TEMPERATURE,
        GAMMA,
        seed=0,
        compile=compile,
    ).to(device)
    return lambda x: planner(x)


def make_pytorch_mppi(K: int, H: int, device: str) -> Callable[[torch.Tensor], object] | None:
    try:
        from pytorch_mppi import MPPI as PMPPI
    except ImportError:
        return None
    goal = torch.tensor(GOAL, device=device)
    centers = torch.tensor([c for c, _ in ELLIPSES], device=device)
    axes = torch.tensor([a for _, a in ELLIPSES], device=device)

    def dynamics(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        v, th = x[:, 2], x[:, 3]
        xdot = torch.stack([v * torch.cos(th), v * torch.sin(th), u[:, 0], u[:, 1]], -1)
        return x + DT * xdot

    def running_cost(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p = x[:, :2]
        b = (((p.unsqueeze(1) - centers) / axes) ** 2).sum(-1) - 1.0
        return 2.0 * ((p - goal) ** 2).sum(-1) + (2.0 / b.clamp_min(0.01)).sum(-1)

    def terminal(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return 10.0 * ((states[..., -1, :2] - goal) ** 2).sum(-1)

    planner = PMPPI(
        dynamics,
        running_cost,
        4,
        torch.eye(2, device=device),
        num_samples=K,
        horizon=H,
        terminal_state_cost=terminal,
        lambda_=TEMPERATURE,
        device=device,
    )
    return lambda x: planner.command(x)


def timed(step: Callable[[torch.Tensor], object], x: torch.Tensor, warmup: int, reps: int):
    t = time.perf_counter()
    for _ in range(warmup):
        step(x)
    first = time.perf_counter() - t
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        step(x)
        times.append(time.perf_counter() - t)
    times.sort()
    return times[len(times) // 2], first


def run_one(name: str, K: int, H: int, reps: int, device: str) -> dict[str, float]:
    """One planner in this process: median s/step, first calls (incl. compile), peak memory."""
    x0 = torch.tensor([0.0, 0.0, 0.0, math.pi / 4], device=device)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if name == "pytorch-mppi":
        step = make_pytorch_mppi(K, H, device)
        if step is None:
            return {}
    else:
        step = make_torchcbf(K, H, name == "compiled", device)
    med, first = timed(step, x0, 2, reps)
    if device == "cuda":
        peak = torch.cuda.max_memory_allocated() / 2**20
    else:  # growth of the process's peak resident set over the imports
        peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_rss) / 1024
    return {"median": med, "first": first, "peak_mib": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="(1000, 50) only, 3 repeats")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--reps", type=int, default=7)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled planner")
    parser.add_argument("--one", nargs=3, metavar=("NAME", "K", "H"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    reps = 3 if args.quick else args.reps
    if args.one:
        name, K, H = args.one[0], int(args.one[1]), int(args.one[2])
        print(json.dumps(run_one(name, K, H, reps, args.device)))
        return
    sizes = [(1000, 50)] if args.quick else [(1000, 50), (10000, 50), (20000, 80)]
    names = ["pytorch-mppi", "eager"] + ([] if args.no_compile else ["compiled"])
    print(f"torch {torch.__version__}, {args.threads} threads, float32, {args.device}")
    print("median time per planning step; first = the 2 warm-up calls (incl. compile);")
    print("peak = growth of peak RSS in a fresh process (CPU) or max_memory_allocated (CUDA)")
    print(
        f"{'K':>6} {'H':>3}  {'planner':<18} {'s/step':>9} {'first s':>8} {'ratio':>7}"
        f" {'peak MiB':>9}"
    )
    for K, H in sizes:
        ref = None
        for name in names:
            cmd = [sys.executable, __file__, "--one", name, str(K), str(H)]
            cmd += ["--threads", str(args.threads), "--reps", str(reps), "--device", args.device]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            label = {"pytorch-mppi": "pytorch-mppi 0.9.1", "eager": "torchcbf eager"}.get(
                name, "torchcbf compiled"
            )
            if not res:
                print(f"{K:>6} {H:>3}  {label:<18} not installed, skipped")
                continue
            if name == "pytorch-mppi":
                ref = res["median"]
            ratio = f"{res['median'] / ref:7.2f}" if ref else "    n/a"
            print(
                f"{K:>6} {H:>3}  {label:<18} {res['median']:9.4f} {res['first']:8.2f} {ratio}"
                f" {res['peak_mib']:9.0f}"
            )


if __name__ == "__main__":
    main()
