"""Arm reaching past an obstacle: a CLF nominal + CBF-QP filter on link spheres.

A batch of scenarios, each a random collision-free start configuration ``q0`` and a target
POINT, run in lockstep with :func:`torchcbf.sim.simulate`. The filter keeps collision spheres
on the links out of a ball obstacle (and the joints inside their limits). Nominal controllers
(``--nominal``):

- ``ik`` (default): the point target goes through the batched inverse kinematics
  (:meth:`Manipulator.inverse_kinematics`: 8 restarts per target in one batch, collision
  spheres clear of the obstacle by ``path_clearance`` (3 cm), joints 0.06 rad inside their
  limits, the solution nearest to ``q0``). The resulting configuration ``q_goal`` is
  driven to by :class:`RoadmapController`: the joint-space CLF ``qdot = -k (q - w)``
  (``V = |q - w|^2``, velocity-saturated) toward the waypoints ``w`` of a C-space path
  ``q0 -> ... -> q_goal`` on a small shared roadmap (:func:`_roadmap_paths`: 128 random
  collision-free nodes, straight edges checked at 32 points with 3 cm clearance; the
  direct edge when it passes), with a batched deadlock escape: rows that stop moving away
  from their waypoint (held by the filter in front of the obstacle) re-plan from where they
  are to a roadmap node whose segment from the current configuration is clear.
  ``--direct`` starts every row straight toward ``q_goal`` (the roadmap then only serves
  the escape); ``--no-escape`` switches the escape off.
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
by ``--margin`` (covering the zero-order hold between filter calls), and the reported
``min_clearance`` is the un-inflated barrier ``|p_s - c| - (r_s + R)`` over every sphere and
step; ``safe`` means ``>= -1e-6``. ``deadlocks``: rows that missed with a sphere within 2 cm
of the inflated obstacle at the end.

Usage:
    python scripts/arm_reach.py --num 1000 --out arm_reach.png
    python scripts/arm_reach.py --num 1000 --nominal cartesian  # resolved rate
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
    nominal: nn.Module  # ResolvedRateController or RoadmapController
    q0: Tensor  # [B, dof]
    target: Tensor  # [B, 3]
    q_target: Tensor  # [B, dof] the configuration that generated each target
    q_goal: Tensor  # [B, dof] the configuration the nominal drives to (IK or q_target)
    reachable: Tensor  # [B] bool: IK found a collision-free solution within the joint limits
    path_found: Tensor  # [B] bool: a checked C-space path (direct or one via) exists
    has_via: Tensor  # [B] bool: that path goes through a via-configuration
    waypoints: Tensor | None  # [B, W, dof] the planned path (None: not planned)


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


@dataclass
class Roadmap:
    """A shared C-space roadmap and, per scenario, its connections to the target.

    ``nodes [N, dof]``; ``dist [N, N]`` shortest path lengths between nodes and ``nxt [N, N]``
    the next hop from ``i`` toward ``j``; ``to_target [B, N]`` the straight edge length node
    -> target configuration (``inf`` where not clear); ``exit [B, N]`` the last node of the
    best path from each node to the target and ``cost_to_go [B, N]`` its length."""

    nodes: Tensor
    dist: Tensor
    nxt: Tensor
    to_target: Tensor
    exit: Tensor
    cost_to_go: Tensor
    first: Tensor  # [B] first waypoint of each planned path: a node, or -1 (the target)


def _roadmap_paths(
    arm: Manipulator,
    barrier: LinkSphereBarrier,
    q0: Tensor,
    qt: Tensor,
    clearance: float,
    gen: torch.Generator,
    nodes: int = 128,
) -> tuple[Tensor, Tensor, Tensor, Roadmap]:
    """Waypoint paths in C-space from a small roadmap (setup time, not in the control loop).

    Edges are straight joint-space segments whose sphere clearance, checked at 32 points
    (:func:`_segment_clearance`), is ``>= clearance``. The direct edge ``q0 -> qt`` is used
    where it passes; elsewhere the shortest path (joint-space length) ``q0 -> v_i -> ... ->
    v_j -> qt`` through ``nodes`` random configurations (shared by all scenarios, clear by
    ``2 clearance``) connected by such edges (all-pairs shortest paths, Floyd-Warshall).
    Returns ``waypoints [B, W, dof]`` (the path, then ``qt``; ``qt`` only where the direct
    edge passes or no path was found), ``found [B]``, ``has_via [B]`` (bool) and the
    :class:`Roadmap` (for re-planning in :class:`RoadmapController`).
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
    cost_to_go, exit_node = (dist[None] + d1[:, None, :]).min(-1)  # [B, N]
    first = torch.where(has_via, first, torch.full_like(first, -1))
    roadmap = Roadmap(cand, dist, nxt, d1, exit_node, cost_to_go, first)
    return wps, direct | has_via, has_via, roadmap


class RoadmapController(nn.Module):
    """Joint-space CLF nominal along a roadmap path, with a batched deadlock escape.

    Each row follows straight C-space segments ``p -> w``: from its start (or the node it
    last passed, or where it last re-planned) to its current waypoint ``w``, a roadmap node
    (``goal >= 0``) or the target configuration (``goal = -1``). The nominal is the CLF
    ``qdot = -k (q - c)`` (a :class:`JointSpaceController`, velocity-saturated) toward a
    carrot ``c`` on the segment ``lookahead`` (rad) ahead of the projection of ``q``, so the
    arm tracks the segment that the planner checked instead of cutting corners; at the end
    of the segment ``c = w``. A row advances to the next hop when ``|q - w| < switch``.

    Deadlock escape: every ``window`` calls, a row more than ``0.05`` rad from its waypoint
    whose distance to it shrank by less than ``progress`` (rad) since the previous check,
    toward the same waypoint, is stuck (held by the CBF filter in front of the obstacle).
    Its waypoint is banned for that row, and up to ``replan_rows`` stuck rows (``topk``: a
    fixed size, no host sync) re-plan from where they are: the new waypoint is the node
    ``v`` within ``radius`` (rad), neither banned nor the waypoint it was stuck on,
    minimising ``|q - v| + cost_to_go(v)`` (or the target itself) whose straight segment
    from ``q`` keeps the clearance (checked at 16 points, ``>= min(clearance, h(q)) -
    1e-3``). A row whose next hop is banned re-plans too (checked every ``window`` calls).
    Call :meth:`reset` before a new run.
    """

    def __init__(
        self,
        arm: Manipulator,
        roadmap: Roadmap,
        barrier: LinkSphereBarrier,
        q_target: Tensor,
        q_start: Tensor,
        *,
        gain: float = 6.0,
        lookahead: float = 0.3,
        switch: float = 0.15,
        escape: bool = True,
        window: int = 10,
        progress: float = 0.01,
        replan_rows: int = 32,
        radius: float = 1.5,
        clearance: float = 0.03,
    ) -> None:
        super().__init__()
        self.roadmap = roadmap
        self.barrier = barrier
        N = roadmap.nodes.shape[0]
        self.register_buffer("q_target", q_target.clone())
        self.register_buffer("q_start", q_start.clone())
        self.register_buffer("goal", roadmap.first.clone())
        self.register_buffer("prev", q_start.clone())
        self.register_buffer("mark", torch.full_like(q_target[:, 0], math.inf))
        self.register_buffer("mark_goal", roadmap.first.clone())
        self.register_buffer(
            "banned", torch.zeros_like(q_target[:, :1].expand(-1, N + 1), dtype=torch.bool)
        )
        self.register_buffer("replans", torch.zeros_like(roadmap.first))
        self.ctrl = JointSpaceController(arm, q_target, gain=gain)
        self.lookahead = float(lookahead)
        self.switch = float(switch)
        self.escape = bool(escape)
        self.window = int(window)
        self.progress = float(progress)
        self.replan_rows = int(replan_rows)
        self.radius = float(radius)
        self.clearance = float(clearance)
        self.calls = 0

    def reset(self) -> None:
        """Back to the start of the planned paths."""
        self.goal = self.roadmap.first.clone()
        self.prev = self.q_start.clone()
        self.mark = torch.full_like(self.mark, math.inf)
        self.mark_goal = self.goal.clone()
        self.banned = torch.zeros_like(self.banned)
        self.replans = torch.zeros_like(self.replans)
        self.calls = 0

    def _waypoint(self) -> Tensor:
        node = self.roadmap.nodes[self.goal.clamp_min(0)]
        return torch.where((self.goal >= 0)[:, None], node, self.q_target)

    def _slot(self, goal: Tensor) -> Tensor:
        """Column of ``banned`` for a goal: the node, or ``N`` for the target."""
        return torch.where(goal >= 0, goal, self.banned.shape[1] - 1)

    def _advance(self, q: Tensor) -> None:
        """Move to the next hop where the waypoint is reached."""
        w = self._waypoint()
        near = ((q - w).norm(dim=-1) < self.switch) & (self.goal >= 0)
        g = self.goal.clamp_min(0)
        ex = self.roadmap.exit.gather(1, g[:, None])[:, 0]
        hop = torch.where(ex == g, torch.full_like(g, -1), self.roadmap.nxt[g, ex])
        self.prev = torch.where(near[:, None], w, self.prev)
        self.goal = torch.where(near, hop, self.goal)

    def _replan(self, q: Tensor, stuck: Tensor) -> None:
        M = min(self.replan_rows, q.shape[0])
        score = stuck.to(q.dtype) * (1.0 + (q - self.q_target).norm(dim=-1))
        rows = score.topk(M).indices  # [M], stuck rows first
        sel = stuck[rows]
        qs = q[rows]
        nodes = self.roadmap.nodes
        N = nodes.shape[0]
        options = torch.cat([nodes.expand(M, -1, -1), self.q_target[rows, None]], 1)  # [M,N+1,d]
        s = torch.linspace(0.0, 1.0, 16, dtype=q.dtype, device=q.device)[:, None, None, None]
        pts = qs[:, None] + s * (options - qs[:, None])  # [16, M, N+1, dof]
        seg = self.barrier(pts).amin(-1).amin(0)  # [M, N+1]
        need = torch.clamp(self.barrier(qs).amin(-1) - 1e-3, max=self.clearance)
        length = (options - qs[:, None]).norm(dim=-1)
        togo = torch.cat([self.roadmap.cost_to_go[rows], torch.zeros_like(length[:, :1])], 1)
        ok = (seg >= need[:, None]) & (length < self.radius) & torch.isfinite(togo)
        current = self._slot(self.goal[rows])
        ok = ok & ~self.banned[rows] & (torch.arange(N + 1, device=q.device) != current[:, None])
        cost = torch.where(ok, length + togo, torch.full_like(length, math.inf))
        best_cost, best = cost.min(-1)
        new = torch.where(best == N, torch.full_like(best, -1), best)
        change = sel & torch.isfinite(best_cost)
        self.goal = self.goal.scatter(0, rows, torch.where(change, new, self.goal[rows]))
        prev_rows = torch.where(change[:, None], qs, self.prev[rows])
        self.prev = self.prev.scatter(0, rows[:, None].expand(-1, q.shape[1]), prev_rows)
        self.replans = self.replans.scatter_add(0, rows, change.to(self.replans.dtype))

    def _carrot(self, q: Tensor) -> Tensor:
        w = self._waypoint()
        d = w - self.prev
        length2 = (d * d).sum(-1, keepdim=True).clamp_min(1e-12)
        s = ((q - self.prev) * d).sum(-1, keepdim=True) / length2
        s = (s.clamp(0.0, 1.0) + self.lookahead / length2.sqrt()).clamp_max(1.0)
        return self.prev + s * d

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [B, dof] -> u [B, dof]``."""
        self._advance(x)
        self.calls += 1
        if self.escape and self.calls % self.window == 0:
            dist = (x - self._waypoint()).norm(dim=-1)
            stuck = (
                (dist > 0.05) & (self.goal == self.mark_goal) & (self.mark - dist < self.progress)
            )
            # a node a row got stuck on is banned for that row (the target never is)
            slot = self._slot(self.goal)[:, None]
            ban = stuck[:, None] & (self.goal >= 0)[:, None]
            self.banned = self.banned.scatter(1, slot, self.banned.gather(1, slot) | ban)
            heading_banned = self.banned.gather(1, slot)[:, 0]
            self._replan(x, stuck | heading_banned)
            self.mark_goal = self.goal.clone()
            self.mark = (x - self._waypoint()).norm(dim=-1)
        self.ctrl.target = self._carrot(x).to(x)
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
    nominal: str = "ik",
    joint_gain: float = 6.0,
    path_clearance: float = 0.03,
    plan_paths: bool = True,
    escape: bool = True,
    follow_roadmap: bool = True,
    ik_restarts: int = 8,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> Scenario:
    """Build the arm, the filter and ``num`` scenarios (deterministic given ``seed``).

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
        waypoints, found, has_via, roadmap = _roadmap_paths(
            arm, collision, q0, q_goal, path_clearance, gen
        )
    else:  # not planned (filter timing): no path known
        found = has_via = no
        waypoints = None
    if nominal == "cartesian":
        ctrl: nn.Module = ResolvedRateController(
            arm, target, gain=gain, damping=0.05, null_space_gain=null_space_gain
        )
    else:
        if not follow_roadmap:
            roadmap.first = torch.full_like(roadmap.first, -1)
        ctrl = RoadmapController(
            arm, roadmap, collision, q_goal, q0, gain=joint_gain, escape=escape
        )
    return Scenario(
        name, arm, collision, inflated, safety_filter, ctrl, q0, target, qt, q_goal,
        reachable, found, has_via, waypoints,
    )  # fmt: skip


def run(
    scenario: Scenario, steps: int = 400, dt: float = 0.02, tol: float = 0.02
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
    collision = _spheres(arm, name, 0.0, dtype).to(device)
    gen = torch.Generator(device=device).manual_seed(0)
    q0 = _sample_free(arm, collision, batch, 0.05, gen, dtype, device)
    target = arm.end_effector(_sample_free(arm, collision, batch, 0.05, gen, dtype, device))
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    res = arm.inverse_kinematics(
        target, q0, restarts=8, barriers=[collision], clearance=0.03, limit_margin=0.06
    )
    sync()
    return time.perf_counter() - start, float(res.converged.double().mean())


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
