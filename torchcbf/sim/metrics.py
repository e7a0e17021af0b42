"""Per-scenario metrics of a :class:`Trajectory` and a summary across the batch."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_finite, check_index, check_number
from torchcbf.sim.trajectory import Trajectory


@dataclass(frozen=True)
class Goal:
    """A goal region: ``|x[index] - center| <= radius``, optionally by time ``deadline``."""

    center: Sequence[float]
    radius: float
    index: tuple[int, ...] = (0, 1)
    deadline: float | None = None

    def __post_init__(self) -> None:
        index = check_index("index", self.index, None)
        center = as_tensor("center", self.center, dtype=torch.float64).reshape(-1)
        check_finite("center", center)
        if center.numel() != len(index):
            raise ValueError(
                f"center has {center.numel()} entries but index names {len(index)} components"
            )
        check_number("radius", self.radius, low=0.0)
        if self.deadline is not None:
            check_number("deadline", self.deadline)


def _least(h: Tensor) -> Tensor:
    """The least barrier value ``[...]`` of ``h [..., k]``; ``+inf`` without any (``k = 0``:
    a filter with Lyapunov functions alone)."""
    if h.shape[-1] == 0:
        return h.new_full(h.shape[:-1], math.inf)
    return h.amin(-1)


def _first_time(mask: Tensor, t: Tensor) -> Tensor:
    """Time of the first True along the last dim of ``mask [B, T]`` (nan where never)."""
    hit = mask.any(-1)
    first = torch.argmax(mask.to(torch.int8), dim=-1)
    return torch.where(hit, t[first], torch.full_like(t[first], float("nan")))


def _barrier_values(
    fns: Sequence[Callable[..., Tensor]], x: Tensor, t: Tensor | None = None
) -> Tensor:
    """Every barrier's values on the states ``x [B, ..., n]`` at the times ``t`` (broadcast
    to ``x``'s batch dimensions) as ``[B, ..., k]``, evaluated on the flattened states, so a
    function needs to take one batch dimension only. A time-varying barrier
    (``time_varying``) is read at the states' own times; other functions take ``x`` alone."""
    if not fns:
        return x.new_zeros(*x.shape[:-1], 0)
    flat = x.reshape(-1, x.shape[-1])
    times = None if t is None else t.to(x).expand(x.shape[:-1]).reshape(-1)

    def value(fn: Callable[..., Tensor], states: Tensor, at: Tensor | None) -> Tensor:
        if at is not None and getattr(fn, "time_varying", False):
            return fn(states, at)
        return fn(states)

    with torch.no_grad():
        if flat.shape[0] == 0:  # no state: each function's outputs counted on a stand-in
            flat = flat.new_zeros(1, flat.shape[-1])
            at = None if times is None else flat.new_zeros(1)
            k = sum(math.prod(value(fn, flat, at).shape[1:]) for fn in fns)
            return x.new_zeros(*x.shape[:-1], k)
        values = [value(fn, flat, times).reshape(flat.shape[0], -1) for fn in fns]
    return torch.cat(values, -1).reshape(*x.shape[:-1], -1)


#: state values of segment points evaluated at once by the swept check (bounds its memory)
SWEPT_CHUNK_ELEMENTS = 2**22


def _swept(
    fns: Sequence[Callable[[Tensor], Tensor]], x: Tensor, t: Tensor, points: int
) -> tuple[Tensor | None, Tensor]:
    """Whether each barrier is negative at each of the ``points`` interior points of the
    straight segments between consecutive samples ``[B, T, points, K]`` (evaluated a few
    steps at a time), and the times of samples and points in order ``[T (points + 1) + 1]``
    (``None`` and the sample times when there is nothing to add)."""
    if points == 0 or x.shape[1] < 2:
        return None, t
    s = torch.arange(1, points + 1, device=x.device, dtype=x.dtype) / (points + 1)
    B, T, n = x.shape[0], x.shape[1] - 1, x.shape[-1]
    steps = max(1, SWEPT_CHUNK_ELEMENTS // max(1, B * points * n))
    between = []
    for j in range(0, T, steps):
        end = min(j + steps, T)
        start = x[:, j:end, None, :]
        step = (x[:, j + 1 : end + 1] - x[:, j:end])[:, :, None, :]
        at = t[j:end, None] + s.to(t) * (t[j + 1 : end + 1] - t[j:end])[:, None]  # [steps, P]
        between.append(_barrier_values(fns, start + s[:, None] * step, at) < 0)
    frac = torch.cat([torch.zeros(1, device=x.device, dtype=x.dtype), s])
    times = (t[:-1, None] + frac * (t[1:] - t[:-1])[:, None]).reshape(-1)
    return torch.cat(between, 1), torch.cat([times, t[-1:]])


def wilson_interval(successes: int, total: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a rate (95% by default): ``0 <= successes <= total``."""
    for name, value in (("successes", successes), ("total", total)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    if successes > total:
        raise ValueError(f"successes ({successes}) must not exceed total ({total})")
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
    segment_points: int = 8,
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
        segment_points: with ``barriers``, the barriers are also evaluated at this many
            evenly spaced points of the straight segment between each two consecutive
            samples (a swept check: a step long enough to jump over an obstacle still counts
            as a collision; an obstacle narrower than the segment's length over
            ``segment_points + 1`` can still slip between the points). 0: samples only.

    Returns:
        ``collision`` (at a sample or, with ``barriers``, between two samples),
        ``collision_between_samples`` (with ``barriers``: a segment crosses an obstacle that
        no sample is inside), ``first_collision_time`` (nan if none; a point between samples
        at its interpolated time), ``min_h`` (over the samples; a frozen row's unrecorded
        steps skipped; ``+inf`` without any barrier), per goal
        ``goal{i}_reached`` and ``goal{i}_time``, ``goal_reached`` (all goals),
        ``spec_robustness``/``spec_satisfied``, ``steps_{name}`` per status, ``effort``
        (``sum |u|^2 dt``) and ``failed``.
    """
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"trajectory must be a Trajectory, got {type(trajectory).__name__}")
    if (
        isinstance(segment_points, bool)
        or not isinstance(segment_points, int)
        or segment_points < 0
    ):
        raise ValueError(f"segment_points must be a non-negative int, got {segment_points!r}")
    traj = trajectory
    t = traj.t
    out: dict[str, Tensor] = {"failed": traj.failed}
    h: Tensor | None = None
    if barriers is not None:
        # a ModuleList is callable (nn.Module) but holds the barriers
        listed = isinstance(barriers, (nn.ModuleList, list, tuple))
        fns = list(barriers) if listed or not callable(barriers) else [barriers]
        h = _barrier_values(fns, traj.x, t)
        h_min = _least(h)
        unsafe = h_min < 0
        out["min_h"] = h_min.amin(-1)
        swept, dense_t = _swept(fns, traj.x, t, segment_points) if fns else (None, t)
        if swept is not None:
            # per obstacle: crossed by a segment, and no sample inside that same one
            crossed = swept.any(2).any(1) & ~(h < 0).any(1)  # [B, K]
            out["collision_between_samples"] = crossed.any(-1)
            between = swept.any(-1)  # [B, T, P]
            # samples and segment points in time order: sample k, then its segment's points
            merged = torch.cat([unsafe[:, :-1, None], between], -1).flatten(1)
            merged = torch.cat([merged, unsafe[:, -1:]], -1)
            out["collision"] = merged.any(-1)
            out["first_collision_time"] = _first_time(merged, dense_t)
        else:
            out["collision"] = unsafe.any(-1)
            out["first_collision_time"] = _first_time(unsafe, t)
    elif traj.h is not None:
        h = traj.h
        h_min = _least(h)
        unsafe = h_min < 0
        out["collision"] = unsafe.any(-1)
        out["first_collision_time"] = _first_time(unsafe, t[:-1])
        # the steps a frozen row did not record (NaN) do not count; NaN where none did
        recorded = ~torch.isnan(h_min)
        least = torch.where(recorded, h_min, torch.inf).amin(-1)
        out["min_h"] = torch.where(recorded.any(-1), least, math.nan)
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
