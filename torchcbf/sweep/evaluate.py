"""One configuration of a scenario, run as one batch of seeds, summarised as one table row.

Success of a seed: the specification holds (scenario A: every goal in its window, the
obstacle never touched) or, without a specification, every goal is reached without any
collision (scenario B: within 0.25 m of the goal by 5 s, no ellipse ever entered).

The objective of :mod:`torchcbf.sweep.tune` is ``success_rate + tie_break / (2 N)`` for
``N`` seeds, so one more success always counts more than any tie-break; the tie-break in
[0, 1) prefers an earlier mean time to goal (``1 - t_goal / T`` over the successful seeds,
``T`` the run's duration; 0 without any) or, for a specification without goal times, a
larger mean robustness (``1/2 + atan(robustness) / pi``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from torchcbf.sim import strict, summarize, wilson_interval
from torchcbf.sweep.params import ScenarioName, builder


def success(per_seed: Mapping[str, Tensor]) -> Tensor:
    """Per-seed success ``[B]`` (bool) from :func:`torchcbf.sim.metrics` output."""
    if "spec_satisfied" in per_seed:
        ok = per_seed["spec_satisfied"].clone()
    elif "goal_reached" in per_seed:
        ok = per_seed["goal_reached"].clone()
    else:
        raise ValueError("per_seed has neither spec_satisfied nor goal_reached")
    if "collision" in per_seed:
        ok = ok & ~per_seed["collision"]
    return ok


def tie_break(per_seed: Mapping[str, Tensor], duration: float) -> float:
    """A number in [0, 1): higher for an earlier time to goal of the successful seeds (or a
    larger mean robustness)."""
    times = [v for k, v in per_seed.items() if k.startswith("goal") and k.endswith("_time")]
    if times:
        t = torch.stack([v.double() for v in times], -1).amax(-1)  # all goals reached
        t = t[torch.isfinite(t) & success(per_seed)]
        if t.numel() == 0:
            return 0.0
        return float((1.0 - t.mean() / duration).clamp(0.0, 1.0 - 1e-9))
    if "spec_robustness" in per_seed:
        rob = float(per_seed["spec_robustness"].double().mean())
        return 0.5 + math.atan(rob) / math.pi if math.isfinite(rob) else 0.0
    return 0.0


def objective(per_seed: Mapping[str, Tensor], duration: float) -> float:
    """``success_rate + tie_break / (2 N)`` (see the module docstring)."""
    ok = success(per_seed)
    n = ok.numel()
    return float(ok.double().mean()) + tie_break(per_seed, duration) / (2 * n)


def _rate(flags: Tensor) -> dict[str, float]:
    k, n = int(flags.sum()), flags.numel()
    lo, hi = wilson_interval(k, n)
    return {"rate": k / n, "count": k, "ci95_low": lo, "ci95_high": hi}


def evaluate(
    scenario: ScenarioName,
    params: Mapping[str, Any],
    *,
    num_seeds: int,
    seed: int,
    device: str = "cpu",
    threads: int = 1,
) -> dict[str, Any]:
    """Build ``scenario`` (a registered name or an entry) with ``params``, run seeds
    ``seed .. seed + num_seeds - 1`` as one batch, return one row: the parameters,
    success/collision/goal rates with 95% Wilson intervals, the mean time to goal (s), the
    minimum barrier value, the objective and the wall time. The run uses ``threads`` torch
    threads (restored afterwards) so that every engine computes the same numbers.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        scenario_run = builder(scenario)(**params, num_seeds=num_seeds, seed=seed, device=device)
        start = time.perf_counter()
        _, per_seed = scenario_run.run(progress=False)
        seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(previous)
    per_seed = {k: v.detach().cpu() for k, v in per_seed.items()}
    duration = scenario_run.steps * scenario_run.dt
    summary = summarize(per_seed)
    ok = success(per_seed)
    row: dict[str, Any] = {k: strict(v) for k, v in params.items()}
    row.update(
        {
            "num_seeds": num_seeds,
            "first_seed": seed,
            **{f"success_{k}": v for k, v in _rate(ok).items()},
        }
    )
    if "collision" in per_seed:
        row.update({f"collision_{k}": v for k, v in _rate(per_seed["collision"]).items()})
    if "goal_reached" in per_seed:
        row.update({f"goal_{k}": v for k, v in _rate(per_seed["goal_reached"]).items()})
        times = [k for k in per_seed if k.startswith("goal") and k.endswith("_time")]
        row["time_to_goal_s"] = summary[times[-1]]["mean"] if times else None
    if "spec_robustness" in per_seed:
        row["spec_robustness_mean"] = summary["spec_robustness"]["mean"]
    if "min_h" in summary:
        row["min_h"] = summary["min_h"]["min"]
    row["objective"] = objective(per_seed, duration)
    row["wall_s"] = seconds
    return row
