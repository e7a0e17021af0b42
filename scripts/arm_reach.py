"""Arm reaching past an obstacle: a CLF nominal + CBF-QP filter on link spheres.

A batch of scenarios, each a random collision-free start configuration ``q0`` and a target,
run in lockstep with :func:`torchcbf.sim.simulate`. The filter keeps collision spheres on the
links out of a ball obstacle (and the joints inside their limits). Two nominal controllers
(``--nominal``):

- ``joint`` (default): the target is given as a CONFIGURATION. Each target point is
  generated as ``ee(q*)`` of a random configuration ``q*`` and this generating ``q*`` is
  handed to the controller (no IK is solved): the task is "reach a target configuration".
  The nominal is the joint-space CLF ``qdot = -k (q - w)`` (``V = |q - w|^2``, velocity-
  saturated) toward the waypoints ``w`` of a C-space path ``q0 -> ... -> q*`` planned once
  at setup on a small shared roadmap (:func:`_roadmap_paths`: 128 random collision-free
  nodes, straight edges checked at 32 points with 3 cm clearance; the direct edge when it
  passes). The waypoints are the documented escape from CBF deadlocks at the obstacle; the
  straight joint-space segments stay inside the joint-limit box, so no joint-limit stalls.
- ``cartesian``: the target is the POINT; the nominal is the damped least-squares resolved
  rate ``qdot = J^+ k (target - ee)`` with joint centring in the null space (greedy and
  local: it stalls at joint limits and in front of the obstacle).

Reachable targets (both variants get the same scenarios): ``q*`` is drawn uniformly within
the joint limits shrunk by 0.15 rad, every collision sphere at ``q*`` clears the obstacle by
``clearance`` (5 cm), the target point is at least ``clearance`` from the obstacle surface
and in the annulus of ``GEOMETRY``. This is what "reachable" means here: the target
configuration is valid with margin. Whether a collision-free path to it exists is NOT
decided exactly; ``path_found_rate`` reports how often the roadmap found a checked path
(discretised check of straight segments), and ``reach_rate_path_found`` the reach rate
among those. Reached: final end-effector error below 2 cm (both variants).

Safety is checked on the true geometry: the filter enforces the barrier on spheres inflated
by ``--margin`` (covering the zero-order hold between filter calls), and the reported
``min_clearance`` is the un-inflated barrier ``|p_s - c| - (r_s + R)`` over every sphere and
step; ``safe`` means ``>= -1e-6``.

Usage:
    python scripts/arm_reach.py --num 1000 --out arm_reach.png
    python scripts/arm_reach.py --num 1000 --nominal cartesian  # target as a point
    python scripts/arm_reach.py --quick                # 64 scenarios, short
    python scripts/arm_reach.py --arm arm7 --num 256   # the 7-joint arm
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchcbf.barriers.workspace import JointLimitBarrier, LinkSphereBarrier
from torchcbf.dynamics.manipulator import (
    JointSpaceController,
    Manipulator,
    ResolvedRateController,
)
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
    nominal: nn.Module  # ResolvedRateController or ViaPointController
    q0: Tensor  # [B, dof]
    target: Tensor  # [B, 3]
    q_target: Tensor  # [B, dof] the configuration that generated each target
    path_found: Tensor  # [B] bool: a checked C-space path (direct or one via) exists
    has_via: Tensor  # [B] bool: that path goes through a via-configuration


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


def _segment_clearance(
    barrier: LinkSphereBarrier, qa: Tensor, qb: Tensor, samples: int = 32
) -> Tensor:
    """Smallest barrier value along the straight joint-space segments ``qa -> qb`` (both
    ``[B, dof]``), checked at ``samples`` evenly spaced points: ``[B]``. A discretised
    check (not a proof): consecutive points are at most ``|qb - qa| / (samples - 1)`` apart."""
    s = torch.linspace(0.0, 1.0, samples, dtype=qa.dtype, device=qa.device)[:, None, None]
    q = qa + s * (qb - qa)  # [samples, B, dof]
    return barrier(q).amin(-1).amin(0)


def _roadmap_paths(
    arm: Manipulator,
    barrier: LinkSphereBarrier,
    q0: Tensor,
    qt: Tensor,
    clearance: float,
    gen: torch.Generator,
    nodes: int = 128,
) -> tuple[Tensor, Tensor, Tensor]:
    """Waypoint paths in C-space from a small roadmap (setup time, not in the control loop).

    Edges are straight joint-space segments whose sphere clearance, checked at 32 points
    (:func:`_segment_clearance`), is ``>= clearance``. The direct edge ``q0 -> qt`` is used
    where it passes; elsewhere the shortest path (joint-space length) ``q0 -> v_i -> ... ->
    v_j -> qt`` through ``nodes`` random configurations (shared by all scenarios, clear by
    ``2 clearance``) connected by such edges (all-pairs shortest paths, Floyd-Warshall).
    Returns ``waypoints [B, W, dof]`` (the path, then ``qt``; ``qt`` only where the direct
    edge passes or no path was found), ``found [B]`` and ``has_via [B]`` (bool).
    """
    inf = math.inf
    cand = _sample_free(arm, barrier, nodes, 2 * clearance, gen, q0.dtype, q0.device)
    N, B = cand.shape[0], q0.shape[0]
    direct = _segment_clearance(barrier, q0, qt) >= clearance
    # node-node edges
    ia, ib = torch.triu_indices(N, N, 1, device=q0.device)
    ok = _segment_clearance(barrier, cand[ia], cand[ib]) >= clearance
    dist = torch.full((N, N), inf, dtype=q0.dtype, device=q0.device)
    length = (cand[ia] - cand[ib]).norm(dim=-1)
    dist[ia, ib] = torch.where(ok, length, inf)
    dist[ib, ia] = dist[ia, ib]
    dist.fill_diagonal_(0.0)
    nxt = torch.arange(N, device=q0.device).expand(N, N).clone()  # next hop from i toward j
    for k in range(N):  # Floyd-Warshall over the shared roadmap
        alt = dist[:, k : k + 1] + dist[k : k + 1, :]
        better = alt < dist
        dist = torch.where(better, alt, dist)
        nxt = torch.where(better, nxt[:, k : k + 1].expand(N, N), nxt)
    # scenario-node edges (a loop over nodes, each batched over scenarios)
    d0 = torch.full((B, N), inf, dtype=q0.dtype, device=q0.device)
    d1 = torch.full_like(d0, inf)
    for i, v in enumerate(cand):
        vb = v.expand_as(q0)
        ok0 = _segment_clearance(barrier, q0, vb) >= clearance
        ok1 = _segment_clearance(barrier, vb, qt) >= clearance
        d0[:, i] = torch.where(ok0, (vb - q0).norm(dim=-1), inf)
        d1[:, i] = torch.where(ok1, (qt - vb).norm(dim=-1), inf)
    total = d0[:, :, None] + dist[None] + d1[:, None, :]  # [B, N, N]
    best, flat = total.reshape(B, -1).min(-1)
    has_via = torch.isfinite(best) & ~direct
    first, last = flat // N, flat % N
    hops = [first]
    while not bool((hops[-1] == last).all()):  # path reconstruction, < N hops (setup only)
        cur = hops[-1]
        hops.append(torch.where(cur == last, cur, nxt[cur, last]))
    wps = torch.stack([cand[h] for h in hops] + [qt], 1)  # [B, W, dof]
    wps = torch.where(has_via[:, None, None], wps, qt[:, None].expand_as(wps))
    return wps, direct | has_via, has_via


class ViaPointController(nn.Module):
    """Joint-space CLF nominal along a waypoint path in C-space (the obstacle escape term).

    ``qdot = -k (q - w_s)`` (a :class:`JointSpaceController`, velocity-saturated) toward
    the current waypoint ``w_s`` of ``waypoints [B, W, dof]``; the stage ``s`` advances when
    ``|q - w_s| < switch`` (rad), and the last waypoint is the target configuration. The
    stage buffer ``[B]`` is updated inside ``forward`` with ``torch.where``/``gather`` (no
    host sync). Call :meth:`reset` before a new run.
    """

    def __init__(
        self, arm: Manipulator, waypoints: Tensor, *, gain: float = 3.0, switch: float = 0.15
    ) -> None:
        super().__init__()
        self.register_buffer("waypoints", waypoints.clone())
        self.register_buffer("stage", torch.zeros_like(waypoints[:, 0, 0], dtype=torch.long))
        self.ctrl = JointSpaceController(arm, waypoints[:, -1], gain=gain)
        self.switch = float(switch)

    def reset(self) -> None:
        """Back to the first waypoint."""
        self.stage = torch.zeros_like(self.stage)

    def _current(self) -> Tensor:
        idx = self.stage[:, None, None].expand(-1, 1, self.waypoints.shape[-1])
        return self.waypoints.gather(1, idx)[:, 0]

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [B, dof] -> u [B, dof]``."""
        near = (x - self._current().to(x)).norm(dim=-1) < self.switch
        last = self.waypoints.shape[1] - 1
        self.stage = torch.where(near, (self.stage + 1).clamp_max(last), self.stage)
        self.ctrl.target = self._current()
        return self.ctrl(x)


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
    nominal: str = "joint",
    joint_gain: float = 3.0,
    path_clearance: float = 0.03,
    plan_paths: bool = True,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> Scenario:
    """Build the arm, the filter and ``num`` scenarios (deterministic given ``seed``).

    ``nominal="cartesian"``: resolved-rate toward the target point (``gain``,
    ``null_space_gain``); ``"joint"``: :class:`ViaPointController` toward the generating
    configuration (``joint_gain``), through a via-configuration where the direct C-space
    segment is not clear. ``plan_paths=False`` skips the roadmap for the Cartesian nominal
    (then ``path_found`` is all False: not planned)."""
    if nominal not in ("cartesian", "joint"):
        raise ValueError(f"nominal must be 'cartesian' or 'joint', got {nominal!r}")
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
    target, qt = target[far], qt[far]
    if target.shape[0] < num:
        raise RuntimeError("too few reachable targets: lower the clearance")
    target, qt = target[:num], qt[:num]
    # the path search runs for both nominals (same generator use, same scenarios)
    if plan_paths or nominal == "joint":
        waypoints, found, has_via = _roadmap_paths(arm, collision, q0, qt, path_clearance, gen)
    else:  # not planned (filter timing): no path known
        found = has_via = torch.zeros_like(qt[:, 0], dtype=torch.bool)
    if nominal == "cartesian":
        ctrl: nn.Module = ResolvedRateController(
            arm, target, gain=gain, damping=0.05, null_space_gain=null_space_gain
        )
    else:
        ctrl = ViaPointController(arm, waypoints, gain=joint_gain)
    return Scenario(
        name, arm, collision, inflated, safety_filter, ctrl, q0, target, qt, found, has_via
    )


def run(
    scenario: Scenario, steps: int = 400, dt: float = 0.02, tol: float = 0.02
) -> dict[str, float | Tensor]:
    """Simulate every scenario; return metrics (and per-scenario tensors for the figure)."""
    sc = scenario
    if isinstance(sc.nominal, ViaPointController):
        sc.nominal.reset()
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
        "path_found_rate": float(sc.path_found.double().mean()),
        "via_rate": float(sc.has_via.double().mean()),
        "reach_rate_path_found": float(reached[sc.path_found].double().mean()),
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
    parser.add_argument(
        "--nominal", choices=["joint", "cartesian"], default="joint",
        help="joint: CLF toward the target configuration (+ via); cartesian: resolved rate",
    )  # fmt: skip
    parser.add_argument("--no-timing", action="store_true", help="skip the filter timing")
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
        qp_backend=args.qp_backend, nominal=args.nominal, dtype=dtype, device=args.device,
    )  # fmt: skip
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
        "non_solved_steps", "failed", "sim_seconds",
    ):  # fmt: skip
        value = result[key]
        print(f"  {key:20s} {value:.6g}" if isinstance(value, float) else f"  {key:20s} {value}")
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
    print(f"  {'arm':8s} {'dtype':8s} {'filter ms':>10s} {'lie ms':>10s}")
    for name in sorted(GEOMETRY):
        for dt_name in ("float32", "float64"):
            sec, lie = time_filter(
                name, args.timing_batch, dtype=getattr(torch, dt_name), device=args.device,
                qp_backend=args.qp_backend,
            )  # fmt: skip
            print(f"  {name:8s} {dt_name:8s} {1e3 * sec:10.2f} {1e3 * lie:10.2f}")


if __name__ == "__main__":
    main()
