"""Per-scenario metrics of a :class:`Trajectory` and a summary across the batch."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcbf.sim.trajectory import Trajectory


@dataclass(frozen=True)
class Goal:
    """A goal region: ``|x[index] - center| <= radius``, optionally by time ``deadline``."""

    center: Sequence[float]
    radius: float
    index: tuple[int, ...] = (0, 1)
    deadline: float | None = None


def _first_time(mask: Tensor, t: Tensor) -> Tensor:
    """Time of the first True along the last dim of ``mask [B, T]`` (nan where never)."""
    hit = mask.any(-1)
    first = torch.argmax(mask.to(torch.int8), dim=-1)
    return torch.where(hit, t[first], torch.full_like(t[first], float("nan")))


def wilson_interval(successes: int, total: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a rate (95% by default)."""
    if total == 0:
        return (0.0, 1.0)
    p = successes / total
    denom = 1 + z * z / total
    centre = (p + z * z / (2 * total)) / denom
    half = z * math.sqrt(p * (1 - p) / total + z * z / (4 * total * total)) / denom
    # rounding can put a bound a hair past the rate itself when it is 0 or 1
    return (min(max(0.0, centre - half), p), max(min(1.0, centre + half), p))


def metrics(
    trajectory: Trajectory,
    barriers: Callable[[Tensor], Tensor] | Sequence[Callable[[Tensor], Tensor]] | None = None,
    goals: Sequence[Goal] = (),
    spec: Any | None = None,
    status_names: dict[int, str] | None = None,
) -> dict[str, Tensor]:
    """Per-scenario metrics, each a tensor with leading dimension B.

    Args:
        barriers: barrier(s) evaluated on the true states (``h >= 0`` safe); each maps
            ``[..., n] -> [...]`` or ``[..., k]``. Without them the filter's recorded ``h``
            (on the estimated state) is used, if any.
        goals: goal regions; a goal counts as reached at the first sampled time inside it
            (and before its ``deadline`` when it has one).
        spec: a specification with ``robustness(states [B, T+1, n], times [T+1]) -> [B]``
            (:mod:`torchcbf.mppi` specs); ``spec_satisfied`` is ``robustness >= 0``.
        status_names: filter status codes to count, ``{code: name}``.

    Returns:
        ``collision``, ``first_collision_time`` (nan if none), ``min_h``, per goal
        ``goal{i}_reached`` and ``goal{i}_time``, ``goal_reached`` (all goals),
        ``spec_robustness``/``spec_satisfied``, ``steps_{name}`` per status, ``effort``
        (``sum |u|^2 dt``) and ``failed``.
    """
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"trajectory must be a Trajectory, got {type(trajectory).__name__}")
    traj = trajectory
    t = traj.t
    out: dict[str, Tensor] = {"failed": traj.failed}
    h: Tensor | None = None
    if barriers is not None:
        fns = [barriers] if callable(barriers) else list(barriers)
        with torch.no_grad():
            values = [fn(traj.x) for fn in fns]
        h = torch.cat([v.reshape(*traj.x.shape[:2], -1) for v in values], dim=-1)
        h_t = t
    elif traj.h is not None:
        h, h_t = traj.h, t[:-1]
    if h is not None:
        h_min = h.min(-1).values
        unsafe = h_min < 0
        out["collision"] = unsafe.any(-1)
        out["first_collision_time"] = _first_time(unsafe, h_t)
        out["min_h"] = h_min.min(-1).values
    all_reached = torch.ones(traj.batch_size, dtype=torch.bool, device=traj.x.device)
    for i, goal in enumerate(goals):
        centre = torch.as_tensor(goal.center, dtype=traj.x.dtype, device=traj.x.device)
        dist = (traj.x[..., list(goal.index)] - centre).norm(dim=-1)
        inside = dist <= goal.radius
        if goal.deadline is not None:
            inside = inside & (t <= goal.deadline + 1e-9)
        out[f"goal{i}_reached"] = inside.any(-1)
        out[f"goal{i}_time"] = _first_time(inside, t)
        out[f"goal{i}_final_distance"] = dist[:, -1]
        all_reached = all_reached & inside.any(-1)
    if goals:
        out["goal_reached"] = all_reached
    if spec is not None:
        with torch.no_grad():
            rob = spec.robustness(traj.x, t)
        out["spec_robustness"] = rob
        out["spec_satisfied"] = rob >= 0
    if traj.status is not None:
        for code, name in (status_names or {}).items():
            out[f"steps_{name}"] = (traj.status == code).sum(-1)
    out["effort"] = (traj.u**2).sum((-1, -2)) * traj.dt
    return out


def summarize(per_scenario: dict[str, Tensor]) -> dict[str, dict[str, float | None]]:
    """Batch summary: rates with 95% Wilson intervals for flags, mean/min/max otherwise.

    Times that are nan (event never happened) are left out of their mean.
    """
    summary: dict[str, dict[str, float | None]] = {}
    for name, value in per_scenario.items():
        v = value.detach().cpu()
        if v.dtype == torch.bool:
            k, total = int(v.sum()), v.numel()
            lo, hi = wilson_interval(k, total)
            summary[name] = {
                "rate": k / max(total, 1),
                "count": k,
                "n": total,
                "ci95_low": lo,
                "ci95_high": hi,
            }
            continue
        v = v.double()
        finite = v[torch.isfinite(v)]
        summary[name] = {
            "mean": float(finite.mean()) if finite.numel() else None,
            "min": float(finite.min()) if finite.numel() else None,
            "max": float(finite.max()) if finite.numel() else None,
            "n": int(finite.numel()),
        }
    return summary
