"""Arm reaching past an obstacle: a CLF nominal + CBF-QP filter on link spheres.

The command-line entry point of :mod:`torchcbf.scenarios.arm_reach` (the scenarios, the
nominal controllers and the metrics are described there): it builds and runs the batch,
prints the metrics and the filter/IK timings, and draws a figure.

Usage:
    python scripts/arm_reach.py --num 1000 --out arm_reach.png
    python scripts/arm_reach.py --num 1000 --nominal cartesian  # resolved rate
    python scripts/arm_reach.py --quick                # 64 scenarios, short
    python scripts/arm_reach.py --arm arm7 --num 256   # the 7-joint arm
"""

from __future__ import annotations

import argparse
import time

import torch

from torchcbf._argtypes import torch_device
from torchcbf.dynamics.manipulator import Manipulator
from torchcbf.roadmap import sample_free_configurations
from torchcbf.scenarios.arm_reach import (
    GEOMETRY,
    ArmReachScenario,
    build,
    link_spheres,
    run,
    top_view,
)


def time_filter(
    name: str = "planar3",
    batch: int = 1024,
    repeats: int = 5,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    qp_backend: str = "torch",
) -> tuple[float, float]:
    """Seconds per filter step (barrier Lie derivatives through FK + batched QP), and of
    the Lie derivatives of the collision spheres alone, at the start states with the
    Cartesian nominal (the filter's cost does not depend on the nominal's form)."""
    sc = build(
        name, batch, dtype=dtype, device=device, qp_backend=qp_backend,
        nominal="cartesian", plan_paths=False,
    )  # fmt: skip
    x = sc.q0
    u_nom = sc.nominal(x)
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    with torch.no_grad():
        sc.safety_filter(x, u_nom)  # warm-up
        sync()
        start = time.perf_counter()
        for _ in range(repeats):
            sc.safety_filter(x, u_nom)
        sync()
        total = (time.perf_counter() - start) / repeats
        start = time.perf_counter()
        for _ in range(repeats):
            sc.inflated.lie(x, sc.arm)
        sync()
        lie = (time.perf_counter() - start) / repeats
    return total, lie


def time_ik(
    name: str = "planar3",
    batch: int = 1024,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
) -> tuple[float, float]:
    """Seconds for one batched IK of ``batch`` point targets (8 restarts, 100 iterations,
    the collision-sphere clearance penalty, as in :func:`build`) and its success rate."""
    device = torch.device(device)
    arm = Manipulator(name).to(device=device, dtype=dtype)
    collision = link_spheres(arm, name, 0.0, dtype).to(device)
    gen = torch.Generator(device=device).manual_seed(0)
    q0 = sample_free_configurations(arm, collision, batch, 0.05, gen, dtype, device)
    target = arm.end_effector(
        sample_free_configurations(arm, collision, batch, 0.05, gen, dtype, device)
    )
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    res = arm.inverse_kinematics(
        target, q0, restarts=8, barriers=[collision], clearance=0.03, limit_margin=0.06
    )
    sync()
    return time.perf_counter() - start, float(res.converged.double().mean())


def plot(sc: ArmReachScenario, result: dict, path: str, shown: int = 12) -> None:
    """Top view (x-y) of end-effector paths, arm poses at start and end, obstacle, targets."""
    title = (
        f"{sc.name}: reach {result['reach_rate']:.1%}, "
        f"min clearance {result['min_clearance']:.4f} m"
    )
    fig = top_view(sc.arm, sc.name, result["x"], sc.target, result["reached"], title=title,
                   shown=shown)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    import matplotlib.pyplot as plt  # after top_view chose the Agg backend

    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arm", choices=sorted(GEOMETRY), default="planar3")
    parser.add_argument("--num", type=int, default=1000, help="scenarios (starts/targets)")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--dt", type=float, default=0.02)
    parser.add_argument("--alpha", type=float, default=5.0)
    parser.add_argument("--margin", type=float, default=0.01, help="sphere inflation (m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", type=torch_device)
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument("--qp-backend", default="torch", help="torch, proxsuite, ...")
    parser.add_argument(
        "--nominal", choices=["ik", "joint", "cartesian"], default="ik",
        help="ik: point target -> IK -> roadmap CLF; joint: CLF toward the generating "
        "configuration; cartesian: resolved rate",
    )  # fmt: skip
    parser.add_argument("--no-escape", action="store_true", help="no deadlock re-planning")
    parser.add_argument(
        "--direct", action="store_true",
        help="start straight toward the target configuration (roadmap only for the escape)",
    )  # fmt: skip
    parser.add_argument("--no-timing", action="store_true", help="skip the filter timing")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--timing-batch", type=int, default=1024)
    parser.add_argument("--timing-only", action="store_true", help="only the filter timing")
    parser.add_argument("--out", default="arm_reach.png", help="figure path ('' for none)")
    parser.add_argument("--quick", action="store_true", help="64 scenarios, 250 steps")
    args = parser.parse_args()
    if args.quick:
        args.num, args.steps = 64, 250
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.timing_only:
        _print_timing(args)
        return
    dtype = getattr(torch, args.dtype)
    setup_start = time.perf_counter()
    sc = build(
        args.arm, args.num, seed=args.seed, alpha=args.alpha, margin=args.margin,
        qp_backend=args.qp_backend, nominal=args.nominal, escape=not args.no_escape,
        follow_roadmap=not args.direct, dtype=dtype, device=args.device,
    )  # fmt: skip
    setup = time.perf_counter() - setup_start
    result = run(sc, args.steps, args.dt)
    print(
        f"arm={args.arm} device={args.device} dtype={args.dtype} dt={args.dt} "
        f"qp_backend={args.qp_backend} nominal={args.nominal} "
        f"threads={torch.get_num_threads()}"
    )
    for key in (
        "scenarios", "steps", "safe_rate", "min_clearance", "min_filter_barrier",
        "reach_rate", "median_final_error", "missed_at_obstacle", "missed_at_joint_limit",
        "missed_other", "path_found_rate", "via_rate", "reach_rate_path_found",
        "reachable_rate", "reach_rate_reachable", "deadlocks", "replans", "rows_replanned",
        "non_solved_steps", "failed", "sim_seconds",
    ):  # fmt: skip
        value = result[key]
        print(f"  {key:20s} {value:.6g}" if isinstance(value, float) else f"  {key:20s} {value}")
    print(f"  {'setup_seconds':20s} {setup:.4g}  (scenarios, IK, roadmap)")
    per_step = result["sim_seconds"] / args.steps
    print(f"  {'seconds_per_step':20s} {per_step:.4g}  (B={args.num}, filter + FK + rk4)")
    if args.no_timing:
        args.timing_batch = 0
    if args.timing_batch > 0:
        _print_timing(args)
    if args.out:
        plot(sc, result, args.out)
        print(f"figure: {args.out}")


def _print_timing(args: argparse.Namespace) -> None:
    print(f"filter step, batch {args.timing_batch} ({args.device}, {args.qp_backend}):")
    print(
        f"  {'arm':8s} {'dtype':8s} {'filter ms':>10s} {'lie ms':>10s} {'ik ms':>10s} {'ik ok':>6s}"
    )
    for name in sorted(GEOMETRY):
        for dt_name in ("float32", "float64"):
            dtype = getattr(torch, dt_name)
            sec, lie = time_filter(
                name, args.timing_batch, dtype=dtype, device=args.device,
                qp_backend=args.qp_backend,
            )  # fmt: skip
            ik, ok = time_ik(name, args.timing_batch, dtype=dtype, device=args.device)
            print(
                f"  {name:8s} {dt_name:8s} {1e3 * sec:10.2f} {1e3 * lie:10.2f} "
                f"{1e3 * ik:10.1f} {ok:6.3f}"
            )


if __name__ == "__main__":
    main()
