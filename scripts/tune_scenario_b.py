"""The sweep that chose scenario B's ``default`` configuration (docs/scenarios.md).

Every grid point runs the filtered methods over a block of tuning seeds (10,000 and up,
never the evaluation seeds 0-31) at a reduced MPPI size, and the rule below picks one:

1. the planner-based methods (``mppi_scbf``, ``shield_mppi``) reach the goal in at least
   30 of 32 seeds (the target rate); points that miss it rank after every point that meets
   it;
2. then the fewest collisions: the sum of the collision rates of the filtered methods
   (``scbf`` may run on more seeds, ``--scbf-seeds``: it is cheap and its rate is the
   largest);
3. then the most goals reached by the planner-based methods;
4. then the larger margins (equilibrium, goal wall, blocking ellipse), then the smaller
   alpha (a gentler filter);
5. then the fewer rollout steps under the shield's discrete-time CBF penalty
   (``--shield-steps``; a cheaper planner). ``scbf`` and ``mppi_scbf`` run once per filter
   point, and their rows count for every value.

Re-applied to the tables of the earlier sweeps (``--rows``), this rule picks the points the
earlier rule picked.

Usage::

    python scripts/tune_scenario_b.py --out docs/tuning    # the grid of docs/scenarios.md
    python scripts/tune_scenario_b.py --alpha 10,20 --margin 0.25 --seeds 8 --workers 1
    python scripts/tune_scenario_b.py --alpha 50 --margin 0.25 --limit 40 \
        --goal-wall-margin none,0.3,0.35,0.4 --seeds 960 --first-seed 50064 --out out/wall
    python scripts/tune_scenario_b.py --alpha 50 --margin 0.25 --limit 40 \
        --goal-wall-margin 0.4 --blocking-margin none,0.275,0.3,0.325 --seeds 960 \
        --scbf-seeds 8192 --first-seed 80000 --out out/blocking
    python scripts/tune_scenario_b.py --alpha 50 --margin 0.25 --limit 40 \
        --goal-wall-margin 0.4 --blocking-margin 0.3 --shield-steps all,1,10,20 \
        --methods mppi_scbf,shield_mppi --seeds 960 --first-seed 300000 --out out/shield

Writes ``tuning.csv`` and ``tuning.md`` (the table) to ``--out`` and prints the choice.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf
from torchcbf.sim import summarize

FILTERED = ("scbf", "mppi_scbf", "shield_mppi")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _optional_floats(text: str) -> list[float | None]:
    """Comma-separated numbers, ``none`` for ``None``."""
    return [None if v.strip() == "none" else float(v) for v in text.split(",") if v.strip()]


def _steps(text: str) -> list[int | None]:
    """Comma-separated step counts, ``all`` for ``None`` (the whole horizon)."""
    return [None if v.strip() == "all" else int(v) for v in text.split(",") if v.strip()]


Job = tuple[
    str, float, float, float | None, float | None, float | None, int | None, int, int, int, int
]


def run_point(job: Job) -> dict[str, object]:
    """One (method, alpha, margin, goal-wall margin, blocking margin, control limit, shield
    steps) over the tuning seeds: counts, wall time."""
    method, alpha, margin, wall, blocking, limit, steps, seeds, first, samples, horizon = job
    torch.set_num_threads(1)
    start = time.perf_counter()
    scenario = mppi_cbf(
        method,
        num_seeds=seeds,
        seed=first,
        num_samples=samples,
        horizon=horizon,
        alpha=alpha,
        margin=margin,
        goal_wall_margin=margin if wall is None else wall,
        blocking_margin=margin if blocking is None else blocking,
        control_limit=limit,
        shield_steps=horizon if steps is None else steps,
    )
    _, per_seed = scenario.run(progress=False)
    s = summarize(per_seed)
    return {
        "method": method,
        "alpha": alpha,
        "margin": margin,
        "goal_wall_margin": "none" if wall is None else wall,
        "blocking_margin": "none" if blocking is None else blocking,
        "control_limit": "none" if limit is None else limit,
        "shield_steps": "all" if steps is None else steps,
        "seeds": seeds,
        "collisions": s["collision"]["count"],
        "goals": s["goal_reached"]["count"],
        "min_b": s["min_h"]["min"],
        "t_goal_mean": s["goal0_time"]["mean"],
        "relaxed_steps_mean": s.get("steps_relaxed", {}).get("mean"),
        "seconds": round(time.perf_counter() - start, 1),
    }


Point = tuple[float, float, float, float, str, str]
TARGET_GOAL_RATE = 30 / 32


def _own_margin(r: dict[str, object], column: str) -> float:
    """The margin of one ellipse in a row (tables of earlier sweeps lack the column)."""
    value = str(r.get(column, "none"))
    return float(r["margin"]) if value == "none" else float(value)


def choose(rows: list[dict[str, object]]) -> Point | None:
    """The grid point ``(alpha, margin, goal-wall margin, blocking margin, control limit,
    shield steps)`` picked by the module docstring's rule (``None`` without rows)."""
    by_filter: dict[tuple[float, float, float, float, str], list[dict[str, object]]] = {}
    for r in rows:
        key = (
            float(r["alpha"]),
            float(r["margin"]),
            _own_margin(r, "goal_wall_margin"),
            _own_margin(r, "blocking_margin"),
            str(r.get("control_limit", "none")),
        )
        by_filter.setdefault(key, []).append(r)
    points: dict[Point, list[dict[str, object]]] = {}
    for key, group in by_filter.items():
        others = [r for r in group if r["method"] != "shield_mppi"]
        shields: dict[str, list[dict[str, object]]] = {}
        for r in group:
            if r["method"] == "shield_mppi":
                shields.setdefault(str(r.get("shield_steps", "all")), []).append(r)
        for steps, shield in (shields or {"all": []}).items():
            points[(*key, steps)] = others + shield

    def planners(point: Point) -> list[dict[str, object]]:
        return [r for r in points[point] if r["method"] != "scbf"]

    def reaches_goals(point: Point) -> bool:
        return all(int(r["goals"]) >= TARGET_GOAL_RATE * int(r["seeds"]) for r in planners(point))

    def collision_rate(point: Point) -> float:
        return sum(int(r["collisions"]) / int(r["seeds"]) for r in points[point])

    if not points:
        return None
    return max(
        points,
        key=lambda p: (
            reaches_goals(p),
            -collision_rate(p),
            sum(int(r["goals"]) for r in planners(p)),
            p[1],
            p[2],
            p[3],
            -p[0],
            -_step_count(p[5]),
        ),
    )


def _step_count(steps: str) -> float:
    """A table's shield steps as a number (``all``: infinity)."""
    return math.inf if steps == "all" else float(steps)


def write_table(rows: list[dict[str, object]], out: Path) -> str:
    """``tuning.csv`` and ``tuning.md`` in ``out``; returns the line naming the choice."""
    with open(out / "tuning.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "| alpha | margin [m] | goal-wall margin [m] | blocking margin [m] | control limit "
        "| shield steps | method | collisions | goal by 5 s | min b | mean t_goal [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t_goal = r["t_goal_mean"]
        t_goal = "-" if t_goal in (None, "") else f"{float(t_goal):.2f}"
        lines.append(
            f"| {float(r['alpha']):g} | {float(r['margin']):g} "
            f"| {_own_margin(r, 'goal_wall_margin'):g} | {_own_margin(r, 'blocking_margin'):g} "
            f"| {r.get('control_limit', 'none')} "
            f"| {r.get('shield_steps', 'all') if r['method'] == 'shield_mppi' else '-'} "
            f"| {r['method']} "
            f"| {r['collisions']}/{r['seeds']} | {r['goals']}/{r['seeds']} "
            f"| {float(r['min_b']):.3f} | {t_goal} |"
        )
    choice = choose(rows)
    verdict = (
        "chosen: nothing (no rows)"
        if choice is None
        else f"chosen: alpha = {choice[0]:g}, margin = {choice[1]:g} m, goal-wall margin "
        f"{choice[2]:g} m, blocking margin {choice[3]:g} m, control limit {choice[4]}, "
        f"shield steps {choice[5]}"
    )
    (out / "tuning.md").write_text("\n".join([*lines, "", verdict]) + "\n")
    return verdict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--alpha", default="20,50", help="alpha values")
    parser.add_argument("--margin", default="0.2,0.25,0.3", help="equilibrium margins (m)")
    parser.add_argument(
        "--goal-wall-margin",
        default="none",
        help="margins (m) of the ellipse at (2, 5) facing the goal ('none': the margin)",
    )
    parser.add_argument(
        "--blocking-margin",
        default="none",
        help="margins (m) of the ellipse at (1, 2) across the start-goal line ('none': the margin)",
    )
    parser.add_argument(
        "--limit", default="none", help="bounds on |a| and |omega| ('none': unbounded)"
    )
    parser.add_argument(
        "--shield-steps",
        default="all",
        help="rollout steps of the shield's penalty ('all': the horizon)",
    )
    parser.add_argument("--methods", default=",".join(FILTERED))
    parser.add_argument("--seeds", type=int, default=16, help="tuning seeds per grid point")
    parser.add_argument("--scbf-seeds", type=int, help="tuning seeds of scbf (default: --seeds)")
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--samples", type=int, default=1000, help="MPPI samples K")
    parser.add_argument("--horizon", type=int, default=80, help="MPPI horizon H")
    parser.add_argument("--workers", type=int, default=2, help="processes (one thread each)")
    parser.add_argument("--out", default="out/tuning")
    parser.add_argument(
        "--rows", help="tabulate this tuning.csv again (no runs): the table and the choice"
    )
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.rows:
        with open(args.rows, newline="") as fh:
            print(write_table(list(csv.DictReader(fh)), out))
        return
    if args.first_seed < 10_000:
        parser.error("tuning seeds start at 10,000 (0-31 are the evaluation seeds)")
    grid = itertools.product(
        _floats(args.alpha),
        _floats(args.margin),
        _optional_floats(args.goal_wall_margin),
        _optional_floats(args.blocking_margin),
        _optional_floats(args.limit),
        args.methods.split(","),
    )
    scbf_seeds = args.seeds if args.scbf_seeds is None else args.scbf_seeds
    shield_steps = _steps(args.shield_steps)
    jobs: list[Job] = [
        (
            m,
            a,
            g,
            w,
            blk,
            lim,
            steps,
            scbf_seeds if m == "scbf" else args.seeds,
            args.first_seed,
            args.samples,
            args.horizon,
        )  # fmt: skip
        for a, g, w, blk, lim, m in grid
        for steps in (shield_steps if m == "shield_mppi" else [None])
    ]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = []
        for row in pool.map(run_point, jobs):
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(write_table(rows, out))


if __name__ == "__main__":
    main()
