"""A C-space roadmap for robot arms, and a joint-space controller that follows it.

:func:`roadmap_paths` plans, for a batch of start and goal configurations, waypoint paths
through a small roadmap shared by the batch: random collision-free nodes
(:func:`sample_free_configurations`) joined by straight joint-space edges whose barrier
clearance, checked at evenly spaced points (:func:`segment_clearance`), stays above a
threshold; all-pairs shortest paths by Floyd-Warshall. :class:`RoadmapController` drives each
row along its path with a joint-space CLF and escapes deadlocks (rows held by a safety
filter in front of an obstacle) by re-planning from where they are.

Planning is setup work (loops over roadmap nodes, a few host syncs); the controller's
``forward`` is batched over rows with no host sync.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchcbf._checks import check_finite, check_number, check_positive_int, check_tensor
from torchcbf.dynamics.manipulator import JointSpaceController, Manipulator

__all__ = [
    "Roadmap",
    "RoadmapController",
    "WorkspaceBarrier",
    "least_barrier",
    "roadmap_paths",
    "sample_free_configurations",
    "sampling_margin",
    "segment_clearance",
]

#: A workspace barrier of the arm: ``q [..., dof] -> h [..., k]`` (e.g. a
#: :class:`~torchcbf.barriers.LinkSphereBarrier`), safe where every entry is ``>= 0``.
WorkspaceBarrier = Callable[[Tensor], Tensor]


def sample_free_configurations(
    arm: Manipulator,
    barrier: WorkspaceBarrier,
    num: int,
    clearance: float,
    gen: torch.Generator,
    dtype: torch.dtype,
    device: torch.device,
    *,
    max_rounds: int = 100,
) -> Tensor:
    """``num`` configurations within the joint limits (0.15 rad or a quarter of a joint's
    range inside, whichever is less) whose barrier values all exceed ``clearance``:
    rejection sampling in rounds of ``4 num`` draws, at most ``max_rounds`` rounds
    (``RuntimeError`` if too few are free: lower the clearance)."""
    num = check_positive_int("num", num)
    max_rounds = check_positive_int("max_rounds", max_rounds)
    clearance = check_number("clearance", clearance)
    found: list[Tensor] = []
    total = 0
    margin = sampling_margin(arm)
    for _ in range(max_rounds):
        q = arm.random_configurations(
            4 * num, generator=gen, margin=margin, dtype=dtype, device=device
        )
        keep = q[least_barrier(barrier, q) > clearance]
        found.append(keep)
        total += keep.shape[0]
        if total >= num:
            return torch.cat(found)[:num]
    raise RuntimeError(
        f"only {total} of {num} configurations clear by {clearance} after {max_rounds} rounds "
        f"of {4 * num} draws: lower the clearance"
    )


def sampling_margin(arm: Manipulator) -> Tensor:
    """How far inside each joint's limits :func:`sample_free_configurations` draws: 0.15 rad,
    or a quarter of the joint's range where that is less (a gripper's slide keeps room)."""
    lo, hi = arm.position_range()
    return ((hi - lo) / 4).clamp_max(0.15)


def least_barrier(barrier: WorkspaceBarrier, q: Tensor) -> Tensor:
    """The least output of ``barrier`` at ``q [..., dof]``: ``[...]`` (a barrier gives
    ``[...]``, one output, or ``[..., k]``)."""
    h = barrier(q)
    return h if h.dim() == q.dim() - 1 else h.amin(-1)


def segment_clearance(
    barrier: WorkspaceBarrier, qa: Tensor, qb: Tensor, samples: int = 32
) -> Tensor:
    """Smallest barrier value along the straight joint-space segments ``qa -> qb`` (both
    ``[B, dof]``), checked at ``samples`` evenly spaced points: ``[B]``. A discretised
    check (not a proof): consecutive points are at most ``|qb - qa| / (samples - 1)`` apart
    (``samples >= 2``: both ends and the points between)."""
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 2:
        raise ValueError(f"samples must be an int >= 2 (both ends), got {samples!r}")
    s = torch.linspace(0.0, 1.0, samples, dtype=qa.dtype, device=qa.device)[:, None, None]
    q = qa + s * (qb - qa)  # [samples, B, dof]
    return least_barrier(barrier, q).amin(0)


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


def roadmap_paths(
    arm: Manipulator,
    barrier: WorkspaceBarrier,
    q0: Tensor,
    qt: Tensor,
    clearance: float,
    gen: torch.Generator,
    nodes: int = 128,
) -> tuple[Tensor, Tensor, Tensor, Roadmap]:
    """Waypoint paths in C-space from a small roadmap (setup time, not in the control loop).

    Edges are straight joint-space segments whose sphere clearance, checked at 32 points
    (:func:`segment_clearance`), is ``>= clearance``. The direct edge ``q0 -> qt`` is used
    where it passes; elsewhere the shortest path (joint-space length) ``q0 -> v_i -> ... ->
    v_j -> qt`` through ``nodes`` random configurations (shared by all scenarios, clear by
    ``2 clearance``) connected by such edges (all-pairs shortest paths, Floyd-Warshall).
    Returns ``waypoints [B, W, dof]`` (the path, then ``qt``; ``qt`` only where the direct
    edge passes or no path was found), ``found [B]``, ``has_via [B]`` (bool) and the
    :class:`Roadmap` (for re-planning in :class:`RoadmapController`).
    """
    inf = math.inf
    dof = arm.dof
    for name, q in (("q0", q0), ("qt", qt)):
        check_tensor(name, q)
        if q.dim() != 2 or q.shape[-1] != dof:
            raise ValueError(f"{name} must have shape [B, {dof}], got {tuple(q.shape)}")
        check_finite(name, q)
    if q0.shape != qt.shape:
        raise ValueError(
            f"q0 {tuple(q0.shape)} and qt {tuple(qt.shape)} must have the same shape [B, {dof}]"
        )
    nodes = check_positive_int("nodes", nodes)
    clearance = check_number("clearance", clearance)
    cand = sample_free_configurations(arm, barrier, nodes, 2 * clearance, gen, q0.dtype, q0.device)
    N, B = cand.shape[0], q0.shape[0]
    direct = segment_clearance(barrier, q0, qt) >= clearance
    # node-node edges
    ia, ib = torch.triu_indices(N, N, 1, device=q0.device)
    ok = segment_clearance(barrier, cand[ia], cand[ib]) >= clearance
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
        ok0 = segment_clearance(barrier, q0, vb) >= clearance
        ok1 = segment_clearance(barrier, vb, qt) >= clearance
        d0[:, i] = torch.where(ok0, (vb - q0).norm(dim=-1), inf)
        d1[:, i] = torch.where(ok1, (qt - vb).norm(dim=-1), inf)
    total = d0[:, :, None] + dist[None] + d1[:, None, :]  # [B, N, N]
    best, flat = total.reshape(B, N * N).min(-1)
    has_via = torch.isfinite(best) & ~direct
    first, last = flat // N, flat % N
    hops = [first]
    for _ in range(N):  # path reconstruction: a shortest path has fewer than N hops
        if bool((hops[-1] == last).all()):
            break
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
        barrier: WorkspaceBarrier,
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
        if arm.control != "velocity":
            raise ValueError(
                "RoadmapController commands joint velocities: it needs an arm with "
                f"control='velocity', got {arm.control!r}"
            )
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
        seg = least_barrier(self.barrier, pts).amin(0)  # [M, N+1]
        need = torch.clamp(least_barrier(self.barrier, qs) - 1e-3, max=self.clearance)
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
