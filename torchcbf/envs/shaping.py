"""Reward shaping for reach-avoid environments: progress along the shortest collision-free
path instead of the straight line.

A reward ``|p - g| - |p' - g|`` (the straight-line progress towards a goal ``g``) points
through an obstacle that lies between the start and the goal; a learner that follows it
crashes, then learns to stop short of the obstacle. :class:`GeodesicProgress` swaps that term
for ``D(p) - D(p')``, where ``D`` is the length of the shortest path to the goal around the
obstacles (:func:`geodesic_distance` on a grid, bilinear in between). Both are potential
differences, so the swap changes the reward by ``Phi(p') - Phi(p)`` with
``Phi = |p - g| - D(p)``: potential-based shaping, which keeps the optimal policies of the
undiscounted task.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.envs import Transform

__all__ = ["DistanceField", "GeodesicProgress", "geodesic_distance"]

_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


class DistanceField(nn.Module):
    """A distance-to-goal field sampled on a regular grid, evaluated by bilinear interpolation.

    ``values [nx, ny]`` at the points ``low + (i, j) * spacing``; ``forward(p [..., 2]) ->
    [...]`` (points outside the grid take the value at the nearest border point).
    """

    def __init__(self, values: Tensor, low: Sequence[float], spacing: float) -> None:
        super().__init__()
        if values.dim() != 2 or min(values.shape) < 2:
            raise ValueError(f"values must be a [nx, ny] grid (nx, ny >= 2), got {values.shape}")
        if not bool(torch.isfinite(values).all()):
            raise ValueError("values must be finite")
        self.register_buffer("values", values)
        self.register_buffer("low", torch.as_tensor(low, dtype=values.dtype))
        self.spacing = float(spacing)

    def forward(self, p: Tensor) -> Tensor:
        """The field at ``p [..., 2]`` (bilinear), ``[...]``."""
        values = self.values.to(p)  # a field left on the CPU serves points on any device
        nx, ny = values.shape
        u = (p - self.low.to(p)) / self.spacing
        finite = torch.isfinite(u).all(-1)  # NaN would index out of the grid: NaN out
        u = torch.where(finite.unsqueeze(-1), u, 0.0)
        ux = u[..., 0].clamp(0, nx - 1)
        uy = u[..., 1].clamp(0, ny - 1)
        ix = ux.floor().clamp(max=nx - 2)
        iy = uy.floor().clamp(max=ny - 2)
        fx, fy = ux - ix, uy - iy
        i, j = ix.long(), iy.long()
        v00, v10 = values[i, j], values[i + 1, j]
        v01, v11 = values[i, j + 1], values[i + 1, j + 1]
        out = (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy
        return torch.where(finite, out, math.nan)


def _relax(dist: Tensor, update: Tensor, spacing: float, max_iter: int) -> Tensor:
    """Bellman-Ford sweeps on the 8-neighbour grid over the cells of ``update``."""
    nx, ny = dist.shape
    for sweep in range(max_iter):
        padded = torch.nn.functional.pad(dist[None, None], (1, 1, 1, 1), value=math.inf)[0, 0]
        best = dist
        for dx, dy in _NEIGHBOURS:
            shifted = padded[1 + dx : 1 + dx + nx, 1 + dy : 1 + dy + ny]
            best = torch.minimum(best, shifted + spacing * math.hypot(dx, dy))
        new = torch.where(update, best, dist)
        if sweep % 16 == 15 and bool(torch.equal(new, dist)):
            return new
        dist = new
    return dist


def _extend_inside(dist: Tensor, is_free: Tensor, spacing: float, max_iter: int) -> Tensor:
    """Continue ``dist`` into the blocked cells: the value of the nearest free cell plus the
    distance to it (so the field grows into the obstacles)."""
    nx, ny = dist.shape
    depth = torch.where(is_free, torch.zeros_like(dist), torch.full_like(dist, math.inf))
    base = torch.where(is_free, dist, torch.zeros_like(dist))
    for _ in range(max_iter):
        pad_depth = torch.nn.functional.pad(depth[None, None], (1, 1, 1, 1), value=math.inf)[0, 0]
        pad_base = torch.nn.functional.pad(base[None, None], (1, 1, 1, 1))[0, 0]
        new_depth, new_base = depth, base
        for dx, dy in _NEIGHBOURS:
            cand = pad_depth[1 + dx : 1 + dx + nx, 1 + dy : 1 + dy + ny] + spacing * math.hypot(
                dx, dy
            )
            better = ~is_free & (cand < new_depth)
            new_depth = torch.where(better, cand, new_depth)
            new_base = torch.where(
                better, pad_base[1 + dx : 1 + dx + nx, 1 + dy : 1 + dy + ny], new_base
            )
        done = bool(torch.equal(new_depth, depth))
        depth, base = new_depth, new_base
        if done:
            break
    return torch.where(is_free, dist, base + depth)


def geodesic_distance(
    free: Callable[[Tensor], Tensor],
    goal: Sequence[float],
    *,
    low: Sequence[float],
    high: Sequence[float],
    spacing: float = 0.05,
    clearance: float = 0.0,
    dtype: torch.dtype = torch.float64,
) -> DistanceField:
    """The length of the shortest path to ``goal`` that stays where ``free`` holds.

    Args:
        free: points ``[..., 2]`` -> bool ``[...]`` (True: outside every obstacle).
        goal: the goal point ``(x, y)``.
        low, high: corners of the grid's box (m).
        spacing: the grid step (m).
        clearance: paths keep at least this distance (m, to the grid's resolution) from the
            obstacles.
        dtype: the field's dtype.

    Paths run on the 8-neighbour grid (their length overestimates the straight one by at
    most 8%); inside the obstacles the field continues with the distance to the nearest free
    cell added, so the field is finite everywhere. Returns a :class:`DistanceField`.
    """
    if not (spacing > 0):
        raise ValueError(f"spacing must be > 0, got {spacing!r}")
    lo = torch.as_tensor(low, dtype=dtype)
    hi = torch.as_tensor(high, dtype=dtype)
    if lo.shape != (2,) or hi.shape != (2,) or not bool((hi > lo).all()):
        raise ValueError(f"low and high must be two points with high > low, got {low}, {high}")
    g = torch.as_tensor(goal, dtype=dtype)
    if g.shape != (2,):
        raise ValueError(f"goal must be a point (x, y), got {goal!r}")
    counts = ((hi - lo) / spacing).floor().long() + 1
    xs = lo[0] + spacing * torch.arange(int(counts[0]), dtype=dtype)
    ys = lo[1] + spacing * torch.arange(int(counts[1]), dtype=dtype)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1)
    is_free = free(grid).to(torch.bool)
    if is_free.shape != grid.shape[:-1]:
        raise ValueError(f"free must return one flag per point {tuple(grid.shape[:-1])}")
    if clearance < 0:
        raise ValueError(f"clearance must be >= 0, got {clearance!r}")
    reach = int(clearance / spacing)
    if reach > 0:  # dilate the obstacles by a disc of radius clearance
        offsets = torch.arange(-reach, reach + 1, dtype=dtype) * spacing
        disc = (offsets[:, None] ** 2 + offsets[None, :] ** 2 <= clearance**2).to(dtype)
        blocked = (~is_free).to(dtype)[None, None]
        hits = torch.nn.functional.conv2d(blocked, disc[None, None], padding=reach)[0, 0]
        is_free = hits < 0.5
    to_goal = (grid - g).norm(dim=-1)
    seed = is_free & (to_goal <= 1.5 * spacing)
    if not bool(seed.any()):
        raise ValueError(f"the goal {tuple(goal)} is not in free space inside the grid")
    dist = torch.where(seed, to_goal, torch.full_like(to_goal, math.inf))
    sweeps = int(counts.prod())
    dist = _relax(dist, is_free & ~seed, spacing, sweeps)
    if not bool(torch.isfinite(dist[is_free]).all()):
        raise ValueError("some free cells of the grid cannot reach the goal")
    dist = _extend_inside(dist, is_free, spacing, sweeps)
    return DistanceField(dist, lo.tolist(), spacing)


class GeodesicProgress(Transform):
    """Swap the straight-line progress in the reward for the progress along the shortest
    collision-free path (see the module docstring).

    ``reward + (D_i(p) - D_i(p')) - (|p - g_i| - |p' - g_i|)`` with ``p``, ``p'`` the positions
    before and after the step (read from ``observation_key`` by ``position_fn``, default the
    first two entries) and ``i`` the index of the current goal (``target_fn`` of the
    observation before the step; default: the only goal).

    Args:
        fields: ``D_i``, one per goal, e.g. from :func:`geodesic_distance`.
        goals: the goals ``g_i`` ``[k, 2]`` (or one point).
        position_fn: observation ``[*B, d]`` -> position ``[*B, 2]``.
        target_fn: observation ``[*B, d]`` -> goal index ``[*B]`` (int64).
        observation_key, reward_key: the entries read and changed.
    """

    def __init__(
        self,
        fields: DistanceField | Sequence[DistanceField],
        goals: Tensor | Sequence[float] | Sequence[Sequence[float]],
        *,
        position_fn: Callable[[Tensor], Tensor] | None = None,
        target_fn: Callable[[Tensor], Tensor] | None = None,
        observation_key: str = "observation",
        reward_key: str = "reward",
    ) -> None:
        fields = [fields] if isinstance(fields, DistanceField) else list(fields)
        if not fields or not all(isinstance(f, DistanceField) for f in fields):
            raise TypeError("fields must be a DistanceField or a sequence of them")
        g = torch.as_tensor(goals, dtype=fields[0].values.dtype).reshape(-1, 2)
        if g.shape[0] != len(fields):
            raise ValueError(
                f"goals {tuple(g.shape)} must have one point per field ({len(fields)})"
            )
        super().__init__(in_keys=[], out_keys=[])
        self.fields = nn.ModuleList(fields)
        self.register_buffer("goals", g)
        self.position_fn = position_fn
        self.target_fn = target_fn
        self.observation_key = observation_key
        self.reward_key = reward_key

    def _position(self, observation: Tensor) -> Tensor:
        if self.position_fn is not None:
            return self.position_fn(observation)
        return observation[..., :2]

    def _progress(self, p: Tensor, q: Tensor, target: Tensor | None) -> Tensor:
        goals = self.goals.to(p)
        straight = (p[..., None, :] - goals).norm(dim=-1) - (q[..., None, :] - goals).norm(dim=-1)
        along = torch.stack([f(p) - f(q) for f in self.fields], dim=-1)
        change = along - straight
        if target is None:
            return change[..., 0]
        return change.gather(-1, target[..., None].long()).squeeze(-1)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.observation_key)
        p = self._position(obs)
        q = self._position(next_tensordict.get(self.observation_key))
        target = None if self.target_fn is None else self.target_fn(obs)
        reward = next_tensordict.get(self.reward_key)
        change = self._progress(p, q, target).unsqueeze(-1).to(reward)
        next_tensordict.set(self.reward_key, reward + change)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Outside an environment the transform does nothing: it acts on the step."""
        return tensordict
