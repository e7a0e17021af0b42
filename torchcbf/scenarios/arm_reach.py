"""Arm reaching past an obstacle: a CLF nominal + CBF-QP filter on link spheres.

Registered as ``arm-reach`` (``torchcbf arm-reach``, ``torchcbf sweep arm-reach``, ...);
``scripts/arm_reach.py`` prints its detailed metrics and the filter and IK timings.

A batch of scenarios, each a random collision-free start configuration ``q0`` and a target
POINT, run in lockstep with :func:`torchcbf.sim.simulate`. The filter keeps collision spheres
on the links out of a ball obstacle (and the joints inside their limits). Nominal controllers
(``nominal=``):

- ``ik`` (default): the point target goes through the batched inverse kinematics
  (:meth:`Manipulator.inverse_kinematics`: 8 restarts per target in one batch, collision
  spheres clear of the obstacle by ``path_clearance`` (3 cm), joints 0.06 rad inside their
  limits, the solution nearest to ``q0``). The resulting configuration ``q_goal`` is
  driven to by :class:`~torchcbf.roadmap.RoadmapController`: the joint-space CLF
  ``qdot = -k (q - w)`` (``V = |q - w|^2``, velocity-saturated) toward the waypoints ``w``
  of a C-space path ``q0 -> ... -> q_goal`` on a small shared roadmap
  (:func:`~torchcbf.roadmap.roadmap_paths`: 128 random collision-free nodes, straight
  edges checked at 32 points with 3 cm clearance; the direct edge when it passes), with a
  batched deadlock escape: rows that stop moving away from their waypoint (held by the
  filter in front of the obstacle) re-plan from where they are to a roadmap node whose
  segment from the current configuration is clear.
  ``follow_roadmap=False`` starts every row straight toward ``q_goal`` (the roadmap then
  only serves the escape); ``escape=False`` switches the escape off.
- ``joint``: the same controller toward the configuration ``q_target`` that generated the
  target (the task "reach a target configuration": no IK).
- ``cartesian``: the damped least-squares resolved rate ``qdot = J^+ k (target - ee)``
  toward the point, with joint centring in the null space (greedy and local: it stalls at
  joint limits and in front of the obstacle).

Scenarios (every variant gets the same ones): ``q_target`` is drawn uniformly within the
joint limits shrunk by 0.15 rad, every collision sphere at ``q_target`` clears the obstacle
by ``clearance`` (5 cm), the target point ``ee(q_target)`` is at least ``clearance`` from the
obstacle surface and in the annulus of ``GEOMETRY``. Every target is therefore reachable
by construction. ``reachable_rate`` reports the definition checked independently of the
generating configuration: the IK (8 restarts) finds a solution within 1e-4 m whose spheres
clear the obstacle and whose joints are within the URDF limits. Whether a collision-free
PATH exists is not decided exactly; ``path_found_rate`` reports how often the roadmap found
a checked one. Reached: final end-effector error below 2 cm (every variant).

Safety is checked on the true geometry: the filter enforces the barrier on spheres inflated
by ``margin`` (covering the zero-order hold between filter calls), and the reported
``min_clearance`` is the un-inflated barrier ``|p_s - c| - (r_s + R)`` over every sphere and
step; ``safe`` means ``>= -1e-6``. ``deadlocks``: rows that missed with a sphere within 2 cm
of the inflated obstacle at the end.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchcbf._checks import check_number, check_positive_int
from torchcbf.barriers.workspace import JointLimitBarrier, LinkSphereBarrier
from torchcbf.dynamics.manipulator import Manipulator, ResolvedRateController
from torchcbf.filters import SafetyFilter
from torchcbf.roadmap import (
    RoadmapController,
    least_barrier,
    roadmap_paths,
    sampling_margin,
)
from torchcbf.scenarios.base import Scenario
from torchcbf.scenarios.registry import Column, Dimension, ScenarioEntry, register
from torchcbf.sim import Trajectory, simulate

__all__ = [
    "GEOMETRY",
    "ArmReachParams",
    "ArmReachScenario",
    "build",
    "build_scenario",
    "top_view",
    "link_spheres",
    "run",
]

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
class ArmReachScenario:
    """The arm, its barriers, filter and nominal controller, and a batch of starts/targets."""

    name: str
    arm: Manipulator
    collision: LinkSphereBarrier  # true geometry
    inflated: LinkSphereBarrier  # what the filter enforces
    safety_filter: SafetyFilter
    nominal: ResolvedRateController | RoadmapController
    q0: Tensor  # [B, dof]
    target: Tensor  # [B, 3]
    q_target: Tensor  # [B, dof] the configuration that generated each target
    q_goal: Tensor  # [B, dof] the configuration the nominal drives to (IK or q_target)
    reachable: Tensor  # [B] bool: IK found a collision-free solution within the joint limits
    path_found: Tensor  # [B] bool: a checked C-space path (direct or one via) exists
    has_via: Tensor  # [B] bool: that path goes through a via-configuration
    waypoints: Tensor | None  # [B, W, dof] the planned path (None: not planned)


def link_spheres(
    arm: Manipulator, name: str, inflate: float, dtype: torch.dtype
) -> LinkSphereBarrier:
    """The collision spheres of arm ``name`` (radii inflated by ``inflate``) against its
    obstacle, as a :class:`~torchcbf.barriers.LinkSphereBarrier` in ``dtype``."""
    geo = GEOMETRY[name]
    links = [s[0] for s in geo["spheres"]]
    offsets = [s[1] for s in geo["spheres"]]
    radii = [s[2] + inflate for s in geo["spheres"]]
    center, radius = geo["obstacle"]
    return LinkSphereBarrier(arm, links, radii, center, radius, offsets=offsets).to(dtype)


#: candidates each row draws per round, for its start and for its target
_CANDIDATES = 8


def _problems(
    name: str, num: int, seed: int, clearance: float, device: torch.device
) -> tuple[Tensor, Tensor]:
    """``(q0, q_target)``, ``[num, dof]`` each: row ``i`` drawn from seed ``seed + i`` alone
    (as every scenario's rows), in float64: the same problems whatever the batch size and
    the run's dtype. A start is a configuration clear of the links' obstacle by
    ``clearance``; a target's end effector also lies clear of it and within the annulus the
    arm reaches well. Each round draws :data:`_CANDIDATES` of each for the rows still
    without one, and checks them all in one call."""
    f64 = torch.float64
    arm = Manipulator(name).to(device=device, dtype=f64)
    collision = link_spheres(arm, name, 0.0, f64).to(device)
    center, radius = GEOMETRY[name]["obstacle"]
    shoulder, r_in, r_out = GEOMETRY[name]["annulus"]
    c = torch.tensor(center, dtype=f64, device=device)
    s = torch.tensor(shoulder, dtype=f64, device=device)
    margin = sampling_margin(arm)
    gens = [torch.Generator(device=device).manual_seed(seed + i) for i in range(num)]
    starts = torch.full((num, arm.dof), math.nan, dtype=f64, device=device)
    targets = starts.clone()
    K = _CANDIDATES
    for _ in range(100):
        rows = (starts.isnan().any(-1) | targets.isnan().any(-1)).nonzero().flatten().tolist()
        if not rows:
            return starts, targets
        q = torch.stack([
            arm.random_configurations(2 * K, generator=gens[i], margin=margin, dtype=f64,
                                      device=device)
            for i in rows
        ])  # fmt: skip
        free = least_barrier(collision, q.flatten(0, 1)).view(len(rows), 2 * K) > clearance
        p = arm.end_effector(q[:, K:].flatten(0, 1)).view(len(rows), K, -1)
        reach = (p - s).norm(dim=-1)
        aims = free[:, K:] & ((p - c).norm(dim=-1) > radius + clearance)
        aims = aims & (reach > r_in) & (reach < r_out)
        for out, ok, cand in ((starts, free[:, :K], q[:, :K]), (targets, aims, q[:, K:])):
            index = torch.tensor(rows, device=device)
            first = ok.to(torch.int8).argmax(-1)
            pick = cand[torch.arange(len(rows), device=device), first]
            take = ok.any(-1) & out[index].isnan().any(-1)
            out[index[take]] = pick[take]
    raise RuntimeError("too few clear starts or reachable targets: lower the clearance")


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
    nominal: str = "ik",
    joint_gain: float = 6.0,
    path_clearance: float = 0.03,
    plan_paths: bool = True,
    escape: bool = True,
    follow_roadmap: bool = True,
    ik_restarts: int = 8,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> ArmReachScenario:
    """Build the arm, the filter and ``num`` scenarios (row ``i`` from seed ``seed + i``, the
    same problem whatever ``num`` and ``dtype``).

    ``nominal="ik"``: the target POINT goes through :meth:`Manipulator.inverse_kinematics`
    (collision spheres clear by ``path_clearance``, joints 0.06 rad inside their limits,
    nearest to ``q0``), then :class:`RoadmapController` drives to that configuration;
    ``"joint"``: the same controller toward the generating configuration ``q_target``;
    ``"cartesian"``: resolved rate toward the target point (``gain``,
    ``null_space_gain``). ``escape`` switches the deadlock escape of
    :class:`RoadmapController`; ``follow_roadmap=False`` starts every row straight toward its
    target configuration (the roadmap is then used only by the escape). ``plan_paths=False``
    skips the roadmap and the IK for the Cartesian nominal (then ``path_found`` and
    ``reachable`` are all False: not computed)."""
    if nominal not in ("cartesian", "joint", "ik"):
        raise ValueError(f"nominal must be 'ik', 'joint' or 'cartesian', got {nominal!r}")
    device = torch.device(device)
    arm = Manipulator(name).to(device=device, dtype=dtype)
    collision = link_spheres(arm, name, 0.0, dtype).to(device)
    inflated = link_spheres(arm, name, margin, dtype).to(device)
    limits = JointLimitBarrier(arm, margin=0.05)
    safety_filter = SafetyFilter(
        arm, barriers=[inflated, limits], alpha=alpha, qp_options={"backend": qp_backend}
    ).to(device, dtype)
    q0, qt = _problems(name, num, seed, clearance, device)
    q0, qt = q0.to(dtype), qt.to(dtype)
    target = arm.end_effector(qt)
    no = torch.zeros_like(qt[:, 0], dtype=torch.bool)
    reachable, q_goal = no, qt
    if plan_paths or nominal != "cartesian":
        # reachable by definition: a collision-free IK solution within the joint limits
        strict = arm.inverse_kinematics(
            target, q0, restarts=ik_restarts, barriers=[collision], seed=seed
        )
        reachable = strict.converged
    if nominal == "ik":
        # the configuration to drive to, with margins for the filter (inflated spheres,
        # joint-limit barrier margin 0.05); a target without one keeps the strict solution
        ik = arm.inverse_kinematics(
            target, q0, restarts=ik_restarts, barriers=[collision], clearance=path_clearance,
            limit_margin=0.06, seed=seed + 1,
        )  # fmt: skip
        q_goal = torch.where(ik.converged[:, None], ik.q, strict.q)
    # the path search runs for every nominal (same generator use, same scenarios)
    if plan_paths or nominal != "cartesian":
        gen = torch.Generator(device=device).manual_seed(seed)  # the roadmap's samples
        waypoints, found, has_via, roadmap = roadmap_paths(
            arm, collision, q0, q_goal, path_clearance, gen
        )
    else:  # not planned (filter timing): no path known
        found = has_via = no
        waypoints = None
    if nominal == "cartesian":
        ctrl: ResolvedRateController | RoadmapController = ResolvedRateController(
            arm, target, gain=gain, damping=0.05, null_space_gain=null_space_gain
        )
    else:
        if not follow_roadmap:
            roadmap.first = torch.full_like(roadmap.first, -1)
        ctrl = RoadmapController(
            arm, roadmap, collision, q_goal, q0, gain=joint_gain, escape=escape
        )
    return ArmReachScenario(
        name, arm, collision, inflated, safety_filter, ctrl, q0, target, qt, q_goal,
        reachable, found, has_via, waypoints,
    )  # fmt: skip


def run(
    scenario: ArmReachScenario, steps: int = 400, dt: float = 0.02, tol: float = 0.02
) -> dict[str, float | Tensor]:
    """Simulate every scenario; return metrics (and per-scenario tensors for the figure)."""
    sc = scenario
    if isinstance(sc.nominal, RoadmapController):
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
        "reachable_rate": float(sc.reachable.double().mean()),
        "reach_rate_reachable": float(reached[sc.reachable].double().mean()),
        "deadlocks": int((missed & blocked).sum()),
        "replans": int(sc.nominal.replans.sum()) if hasattr(sc.nominal, "replans") else 0,
        "rows_replanned": (
            int((sc.nominal.replans > 0).sum()) if hasattr(sc.nominal, "replans") else 0
        ),
        "non_solved_steps": float((status != 0).double().mean()) if status is not None else 0.0,
        "failed": int(traj.failed.sum()),
        "sim_seconds": wall,
        "ee": ee,
        "reached": reached,
        "x": traj.x,
    }


@dataclass(frozen=True)
class ArmReachParams:
    """The parameters of the registered arm scenario (``torchcbf arm-reach``): the arm, the
    filter's ``alpha`` and sphere inflation ``margin``, the nominal controller (see
    :func:`build` for each), the closed loop's ``steps`` of ``dt`` seconds and the reach
    tolerance ``tol`` (m)."""

    arm: str = "planar3"
    nominal: str = "ik"
    alpha: float = 5.0
    margin: float = 0.01
    clearance: float = 0.05
    gain: float = 2.0
    null_space_gain: float = 1.0
    joint_gain: float = 6.0
    path_clearance: float = 0.03
    escape: bool = True
    follow_roadmap: bool = True
    ik_restarts: int = 8
    qp_backend: str = "torch"
    steps: int = 400
    dt: float = 0.02
    tol: float = 0.02


def build_scenario(
    p: ArmReachParams,
    *,
    num_seeds: int = 256,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
) -> Scenario:
    """The arm scenario as a :class:`Scenario`: ``num_seeds`` start/target pairs drawn from
    ``seed``; success is reaching the target within ``tol`` without a collision."""
    check_positive_int("num_seeds", num_seeds)
    check_positive_int("steps", p.steps)
    check_number("dt", p.dt, low=0.0, strict=True)
    check_number("tol", p.tol, low=0.0, strict=True)
    if p.arm not in GEOMETRY:
        raise ValueError(f"arm must be one of {sorted(GEOMETRY)}, got {p.arm!r}")
    sc = build(
        p.arm, num_seeds, seed=seed, alpha=p.alpha, gain=p.gain,
        null_space_gain=p.null_space_gain, margin=p.margin, clearance=p.clearance,
        qp_backend=p.qp_backend, nominal=p.nominal, joint_gain=p.joint_gain,
        path_clearance=p.path_clearance, escape=p.escape, follow_roadmap=p.follow_roadmap,
        ik_restarts=p.ik_restarts, device=device,
        dtype=torch.float64 if dtype is None else dtype,
    )  # fmt: skip
    if isinstance(sc.nominal, RoadmapController):
        sc.nominal.reset()
    target, inflated = sc.target, sc.inflated

    def extra(traj: Trajectory) -> dict[str, Tensor]:
        B, T1, n = traj.x.shape
        ee = sc.arm.end_effector(traj.x.reshape(B * T1, n)).reshape(B, T1, -1)
        errs = (ee - target.unsqueeze(1)).norm(dim=-1)  # [B, T + 1]
        err = errs[:, -1]
        blocked = inflated(traj.x[:, -1]).amin(-1) < 0.02
        inside = errs < p.tol
        # first time within tol of the seeds that end there (nan for the others): what
        # time_to_goal_s averages
        first = torch.argmax(inside.to(torch.int8), dim=-1)
        when = traj.t.to(errs.dtype)[first]
        return {
            "goal_reached": err < p.tol,
            "goal_time": torch.where(err < p.tol, when, torch.nan),
            "final_error": err,
            "missed_at_obstacle": (err >= p.tol) & blocked,
        }

    return Scenario(
        name=f"arm-reach/{p.arm}",
        dynamics=sc.arm,
        x0=sc.q0,
        steps=p.steps,
        dt=p.dt,
        seeds=seed + torch.arange(num_seeds),
        nominal=sc.nominal,
        safety_filter=sc.safety_filter,
        integrator="rk4",
        barriers=[sc.collision],
        goals=[target],
        params={**asdict(p), "num_seeds": num_seeds, "seed": seed},
        extra_metrics=extra,
    )


def top_view(
    arm: Manipulator,
    name: str,
    x: Tensor,
    target: Tensor,
    reached: Tensor,
    *,
    title: str,
    shown: int = 12,
) -> Any:
    """A matplotlib figure, top view (x-y) of arm ``name``'s end-effector paths of the first
    ``shown`` rows of ``x [B, T+1, dof]`` (blue where ``reached [B]``, else orange), the arm
    at the start and the end, the obstacle and the targets ``[B, 3]``."""
    import matplotlib.pyplot as plt  # the user's backend stays (no display: Agg)
    from matplotlib.patches import Circle

    n = min(shown, x.shape[0])
    fig, ax = plt.subplots(figsize=(7, 7))
    center, radius = GEOMETRY[name]["obstacle"]
    ax.add_patch(Circle(center[:2], radius, color="tab:red", alpha=0.35, label="obstacle"))
    e = arm.end_effector(x[:n]).detach().cpu().numpy()
    tgt, ok = target.detach().cpu().numpy(), reached.cpu().numpy()
    for b in range(n):
        color = "tab:blue" if ok[b] else "tab:orange"
        ax.plot(e[b, :, 0], e[b, :, 1], color=color, lw=1)
        ax.plot(tgt[b, 0], tgt[b, 1], "x", color=color, ms=6)
    for pts, style in zip((arm.fk(x[:n, 0]), arm.fk(x[:n, -1])), (":", "-"), strict=True):
        pts = pts.detach().cpu().numpy()
        for b in range(n):
            ax.plot([0.0, *pts[b, :, 0]], [0.0, *pts[b, :, 1]], style, color="0.4", lw=0.8)
    ax.plot([], [], color="tab:blue", label="reached")
    ax.plot([], [], color="tab:orange", label="not reached")
    ax.plot([], [], ":", color="0.4", label="start pose")
    ax.plot([], [], "-", color="0.4", label="final pose")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=8)
    return fig


def figures(
    trajectories: Mapping[str, Trajectory],
    scenario: Scenario,
    out: Path,
    *,
    title: str,
    gif: bool = True,
    first_seed: int = 0,
    shown: int = 12,
) -> list[Path]:
    """:func:`top_view` of the run (``arm_reach.png``; no animation)."""
    from torchcbf.scenarios.figures import save

    (traj,) = trajectories.values()
    arm, target = scenario.dynamics, scenario.goals[0]
    x = traj.x.to(target)
    reached = (arm.end_effector(x[:, -1]) - target).norm(dim=-1) < scenario.params["tol"]
    n = min(shown, x.shape[0])
    title = f"{title}: {n} of {x.shape[0]} rows, reached {reached.double().mean():.0%}"
    fig = top_view(arm, scenario.params["arm"], x, target, reached, title=title, shown=shown)
    return [save(fig, Path(out) / "arm_reach.png")]


ENTRY = register(
    ScenarioEntry(
        name="arm-reach",
        build=build_scenario,
        params=ArmReachParams,
        description=(
            "An arm reaching past a ball obstacle: a CLF nominal (IK + roadmap by default) "
            "and a CBF-QP filter on link spheres and joint limits, one batch of start/target "
            "pairs."
        ),
        search_space=(
            Dimension("alpha", "float", 0.5, 50.0, log=True),
            Dimension("margin", "float", 0.0, 0.05),
            Dimension("joint_gain", "float", 1.0, 20.0, log=True),
        ),
        columns=(
            Column("reached [95% CI]", "goal_reached"),
            Column("collisions [95% CI]", "collision"),
            Column("min clearance [m]", "min_h", "min", "{:.4f}"),
            Column("final error [m]", "final_error", "mean", "{:.4f}"),
        ),
        figures=figures,
        choices={"arm": tuple(GEOMETRY), "nominal": ("ik", "joint", "cartesian")},
        options={"arm": "arm", "nominal": "nominal"},
        units={"min_h": "m (sphere clearance)", "final_error": "m", "seconds": "s"},
        num_seeds=256,
    )
)
