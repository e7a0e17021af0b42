"""Arm reaching past an obstacle: resolved-rate (CLF) nominal + CBF-QP filter on link spheres.

A batch of scenarios, each a random collision-free start configuration and a reachable
target, run in lockstep with :func:`torchcbf.sim.simulate`. The filter keeps collision
spheres on the links out of a ball obstacle (and the joints inside their limits); the
nominal controller is the damped least-squares resolved-rate law ``qdot = J^+ k (target -
ee)``, which decreases ``V = |target - ee|^2``.

Reachable targets: ``target = ee(q_t)`` for a random configuration ``q_t`` within the joint
limits whose collision spheres all clear the obstacle by ``clearance``, with the target at
least ``clearance`` from the obstacle surface. A reachable target can still be missed: the
CBF filter may stop the arm in front of the obstacle (a deadlock, a known limitation of
CBF-QP filters with a greedy nominal), so the reach rate is reported as measured.

Safety is checked on the true geometry: the filter enforces the barrier on spheres inflated
by ``--margin`` (covering the zero-order hold between filter calls), and the reported
``min_clearance`` is the un-inflated barrier ``|p_s - c| - (r_s + R)`` over every sphere and
step; ``safe`` means ``>= -1e-6``.

Usage:
    python scripts/arm_reach.py --num 1000 --out arm_reach.png
    python scripts/arm_reach.py --quick                # 64 scenarios, short
    python scripts/arm_reach.py --arm arm7 --num 256   # the 7-joint arm
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcbf.barriers.workspace import JointLimitBarrier, LinkSphereBarrier
from torchcbf.dynamics.manipulator import Manipulator, ResolvedRateController
from torchcbf.filters import SafetyFilter
from torchcbf.sim import simulate

# Per arm: collision spheres (link, offset in the link frame, radius) and the obstacle.
GEOMETRY = {
    "planar3": {
        "spheres": [
            ("link1", (0.25, 0.0, 0.0), 0.05),
            ("link2", (0.0, 0.0, 0.0), 0.05),
            ("link2", (0.2, 0.0, 0.0), 0.05),
            ("link3", (0.0, 0.0, 0.0), 0.05),
            ("link3", (0.15, 0.0, 0.0), 0.04),
            ("ee", (0.0, 0.0, 0.0), 0.04),
        ],
        "obstacle": ((0.6, 0.45, 0.0), 0.15),
        "annulus": ((0.0, 0.0, 0.0), 0.35, 1.05),  # shoulder, target distance range
    },
    "arm7": {
        "spheres": [
            ("link3", (0.0, 0.0, 0.2), 0.06),
            ("link4", (0.0, 0.0, 0.0), 0.06),
            ("link5", (0.0, 0.0, 0.175), 0.05),
            ("link6", (0.0, 0.0, 0.0), 0.05),
            ("ee", (0.0, 0.0, 0.0), 0.04),
        ],
        "obstacle": ((0.45, 0.15, 0.6), 0.15),
        "annulus": ((0.0, 0.0, 0.25), 0.3, 0.9),
    },
}


@dataclass
class Scenario:
    """The arm, its barriers, filter and nominal controller, and a batch of starts/targets."""

    name: str
    arm: Manipulator
    collision: LinkSphereBarrier  # true geometry
    inflated: LinkSphereBarrier  # what the filter enforces
    safety_filter: SafetyFilter
    nominal: ResolvedRateController
    q0: Tensor  # [B, dof]
    target: Tensor  # [B, 3]


def _spheres(arm: Manipulator, name: str, inflate: float, dtype: torch.dtype) -> LinkSphereBarrier:
    geo = GEOMETRY[name]
    links = [s[0] for s in geo["spheres"]]
    offsets = [s[1] for s in geo["spheres"]]
    radii = [s[2] + inflate for s in geo["spheres"]]
    center, radius = geo["obstacle"]
    return LinkSphereBarrier(arm, links, radii, center, radius, offsets=offsets).to(dtype)


def _sample_free(
    arm: Manipulator,
    barrier: LinkSphereBarrier,
    num: int,
    clearance: float,
    gen: torch.Generator,
    dtype: torch.dtype,
    device: torch.device,
) -> Tensor:
    """``num`` configurations within the joint limits whose spheres clear the obstacle."""
    found: list[Tensor] = []
    total = 0
    while total < num:  # rejection sampling, outside any hot loop
        q = arm.random_configurations(
            4 * num, generator=gen, margin=0.15, dtype=dtype, device=device
        )
        keep = q[(barrier(q) > clearance).all(-1)]
        found.append(keep)
        total += keep.shape[0]
    return torch.cat(found)[:num]


def build(
    name: str = "planar3",
    num: int = 256,
    *,
    seed: int = 0,
    alpha: float = 5.0,
    gain: float = 2.0,
    null_space_gain: float = 1.0,
    margin: float = 0.01,
    clearance: float = 0.05,
    qp_backend: str = "torch",
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> Scenario:
    """Build the arm, the filter and ``num`` scenarios (deterministic given ``seed``)."""
    device = torch.device(device)
    arm = Manipulator(name).to(device=device, dtype=dtype)
    collision = _spheres(arm, name, 0.0, dtype).to(device)
    inflated = _spheres(arm, name, margin, dtype).to(device)
    limits = JointLimitBarrier(arm, margin=0.05)
    safety_filter = SafetyFilter(
        arm, barriers=[inflated, limits], alpha=alpha, qp_options={"backend": qp_backend}
    ).to(device, dtype)
    gen = torch.Generator(device=device).manual_seed(seed)
    q0 = _sample_free(arm, collision, num, clearance, gen, dtype, device)
    qt = _sample_free(arm, collision, 4 * num, clearance, gen, dtype, device)
    target = arm.end_effector(qt)
    center, radius = GEOMETRY[name]["obstacle"]
    c = torch.tensor(center, dtype=dtype, device=device)
    far = (target - c).norm(dim=-1) > radius + clearance
    shoulder, r_in, r_out = GEOMETRY[name]["annulus"]
    reach = (target - torch.tensor(shoulder, dtype=dtype, device=device)).norm(dim=-1)
    far = far & (reach > r_in) & (reach < r_out)
    target = target[far]
    if target.shape[0] < num:
        raise RuntimeError("too few reachable targets: lower the clearance")
    target = target[:num]
    nominal = ResolvedRateController(
        arm, target, gain=gain, damping=0.05, null_space_gain=null_space_gain
    )
    return Scenario(name, arm, collision, inflated, safety_filter, nominal, q0, target)


def run(
    scenario: Scenario, steps: int = 400, dt: float = 0.02, tol: float = 0.02
) -> dict[str, float | Tensor]:
    """Simulate every scenario; return metrics (and per-scenario tensors for the figure)."""
    sc = scenario
    start = time.perf_counter()
    with torch.no_grad():
        traj = simulate(
            sc.arm,
            sc.q0,
            steps,
            dt,
            nominal=sc.nominal,
            safety_filter=sc.safety_filter,
            integrator="rk4",
            progress=False,
        )
    wall = time.perf_counter() - start
    B = traj.x.shape[0]
    clear = sc.collision(traj.x)  # [B, T+1, S]
    ee = sc.arm.end_effector(traj.x)  # [B, T+1, 3]
    err = (ee - sc.target[:, None]).norm(dim=-1)
    reached = err[:, -1] < tol
    min_clear = clear.amin((1, 2))
    # why a scenario missed: at the end, a collision sphere or a joint limit is active
    blocked = sc.inflated(traj.x[:, -1]).amin(-1) < 0.02
    limits = sc.safety_filter.barriers[1](traj.x[:, -1]).amin(-1) < 0.02
    missed = ~reached
    status = traj.status
    return {
        "scenarios": B,
        "steps": steps,
        "safe_rate": float((min_clear >= -1e-6).double().mean()),
        "min_clearance": float(min_clear.min()),
        "min_filter_barrier": float(sc.inflated(traj.x).amin()),
        "reach_rate": float(reached.double().mean()),
        "median_final_error": float(err[:, -1].median()),
        "missed_at_obstacle": float((missed & blocked).double().mean()),
        "missed_at_joint_limit": float((missed & limits & ~blocked).double().mean()),
        "missed_other": float((missed & ~limits & ~blocked).double().mean()),
        "non_solved_steps": float((status != 0).double().mean()) if status is not None else 0.0,
        "failed": int(traj.failed.sum()),
        "sim_seconds": wall,
        "ee": ee,
        "reached": reached,
        "x": traj.x,
    }


def time_filter(
    name: str = "planar3",
    batch: int = 1024,
    repeats: int = 5,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    qp_backend: str = "torch",
) -> tuple[float, float]:
    """Seconds per filter step (barrier Lie derivatives through FK + batched QP), and of
    the Lie derivatives of the collision spheres alone."""
    sc = build(name, batch, dtype=dtype, device=device, qp_backend=qp_backend)
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


def plot(sc: Scenario, result: dict, path: str, shown: int = 12) -> None:
    """Top view (x-y) of end-effector paths, arm poses at start and end, obstacle, targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(7, 7))
    center, radius = GEOMETRY[sc.name]["obstacle"]
    ax.add_patch(Circle(center[:2], radius, color="tab:red", alpha=0.35, label="obstacle"))
    ee = result["ee"].cpu().numpy()
    x = result["x"]
    reached = result["reached"].cpu().numpy()
    tgt = sc.target.cpu().numpy()
    n = min(shown, ee.shape[0])
    for b in range(n):
        color = "tab:blue" if reached[b] else "tab:orange"
        ax.plot(ee[b, :, 0], ee[b, :, 1], color=color, lw=1)
        ax.plot(tgt[b, 0], tgt[b, 1], "x", color=color, ms=6)
    chain = [sc.arm.fk(x[:n, 0]), sc.arm.fk(x[:n, -1])]
    for pts, style in zip(chain, (":", "-"), strict=True):
        pts = pts.cpu().numpy()
        for b in range(n):
            p = pts[b]
            ax.plot([0.0, *p[:, 0]], [0.0, *p[:, 1]], style, color="0.4", lw=0.8)
    ax.plot([], [], color="tab:blue", label="reached")
    ax.plot([], [], color="tab:orange", label="not reached")
    ax.plot([], [], ":", color="0.4", label="start pose")
    ax.plot([], [], "-", color="0.4", label="final pose")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(
        f"{sc.name}: reach {result['reach_rate']:.1%}, "
        f"min clearance {result['min_clearance']:.4f} m"
    )
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
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
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument("--qp-backend", default="torch", help="torch, proxsuite, ...")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--timing-batch", type=int, default=1024)
    parser.add_argument("--out", default="arm_reach.png", help="figure path ('' for none)")
    parser.add_argument("--quick", action="store_true", help="64 scenarios, 250 steps")
    args = parser.parse_args()
    if args.quick:
        args.num, args.steps = 64, 250
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    sc = build(
        args.arm, args.num, seed=args.seed, alpha=args.alpha, margin=args.margin,
        qp_backend=args.qp_backend, dtype=dtype, device=args.device,
    )  # fmt: skip
    result = run(sc, args.steps, args.dt)
    print(
        f"arm={args.arm} device={args.device} dtype={args.dtype} dt={args.dt} "
        f"qp_backend={args.qp_backend} threads={torch.get_num_threads()}"
    )
    for key in (
        "scenarios", "steps", "safe_rate", "min_clearance", "min_filter_barrier",
        "reach_rate", "median_final_error", "missed_at_obstacle", "missed_at_joint_limit",
        "missed_other", "non_solved_steps", "failed", "sim_seconds",
    ):  # fmt: skip
        value = result[key]
        print(f"  {key:20s} {value:.6g}" if isinstance(value, float) else f"  {key:20s} {value}")
    per_step = result["sim_seconds"] / args.steps
    print(f"  {'seconds_per_step':20s} {per_step:.4g}  (B={args.num}, filter + FK + rk4)")
    print(f"filter step, batch {args.timing_batch} ({args.device}, {args.qp_backend}):")
    print(f"  {'arm':8s} {'dtype':8s} {'filter ms':>10s} {'lie ms':>10s}")
    for name in sorted(GEOMETRY):
        for dt_name in ("float32", "float64"):
            sec, lie = time_filter(
                name, args.timing_batch, dtype=getattr(torch, dt_name), device=args.device,
                qp_backend=args.qp_backend,
            )  # fmt: skip
            print(f"  {name:8s} {dt_name:8s} {1e3 * sec:10.2f} {1e3 * lie:10.2f}")
    if args.out:
        plot(sc, result, args.out)
        print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
