"""The sweep that chose scenario B's ``default`` configuration (docs/scenarios.md).

Every grid point runs the filtered methods over a block of tuning seeds (10,000 and up,
never the evaluation seeds 0-31) at a reduced MPPI size, and the rule below picks one:

1. no collision in the planner-based methods (``mppi_scbf``, ``shield_mppi``);
2. then the most goals reached by them;
3. then the fewest collisions of ``scbf`` alone (no grid point keeps it collision-free: a
   stalled unicycle has no lateral authority and the position noise pushes it sideways,
   see docs/scenarios.md);
4. then the larger equilibrium margin, then the smaller alpha (a gentler filter).

Usage::

    python scripts/tune_scenario_b.py --out docs/tuning    # the grid of docs/scenarios.md
    python scripts/tune_scenario_b.py --alpha 10,20 --margin 0.25 --seeds 8 --workers 1

Writes ``tuning.csv`` and ``tuning.md`` (the table) to ``--out`` and prints the choice.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

from torchcbf.scenarios.unicycle_mppi_cbf import mppi_cbf
from torchcbf.sim import summarize

FILTERED = ("scbf", "mppi_scbf", "shield_mppi")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _limits(text: str) -> list[float | None]:
    return [None if v.strip() == "none" else float(v) for v in text.split(",") if v.strip()]


def run_point(job: tuple[str, float, float, float | None, int, int, int, int]) -> dict[str, object]:
    """One (method, alpha, margin, control limit) over the tuning seeds: counts, wall time."""
    method, alpha, margin, limit, seeds, first, samples, horizon = job
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
        control_limit=limit,
    )
    _, per_seed = scenario.run(progress=False)
    s = summarize(per_seed)
    return {
        "method": method,
        "alpha": alpha,
        "margin": margin,
        "control_limit": "none" if limit is None else limit,
        "seeds": seeds,
        "collisions": s["collision"]["count"],
        "goals": s["goal_reached"]["count"],
        "min_b": s["min_h"]["min"],
        "t_goal_mean": s["goal0_time"]["mean"],
        "relaxed_steps_mean": s.get("steps_relaxed", {}).get("mean"),
        "seconds": round(time.perf_counter() - start, 1),
    }


def choose(rows: list[dict[str, object]]) -> tuple[float, float, str] | None:
    """The grid point picked by the module docstring's rule (``None`` if none is safe)."""
    points: dict[tuple[float, float, str], list[dict[str, object]]] = {}
    for r in rows:
        key = (float(r["alpha"]), float(r["margin"]), str(r.get("control_limit", "none")))
        points.setdefault(key, []).append(r)

    def count(point: tuple[float, float, str], key: str, planners: bool) -> int:
        return sum(int(r[key]) for r in points[point] if (r["method"] != "scbf") == planners)

    safe = [p for p in points if count(p, "collisions", True) == 0]
    if not safe:
        return None
    return max(
        safe,
        key=lambda p: (count(p, "goals", True), -count(p, "collisions", False), p[1], -p[0]),
    )


def write_table(rows: list[dict[str, object]], out: Path) -> str:
    """``tuning.csv`` and ``tuning.md`` in ``out``; returns the line naming the choice."""
    with open(out / "tuning.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "| alpha | margin [m] | control limit | method | collisions | goal by 5 s | min b "
        "| mean t_goal [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t_goal = r["t_goal_mean"]
        t_goal = "-" if t_goal in (None, "") else f"{float(t_goal):.2f}"
        lines.append(
            f"| {float(r['alpha']):g} | {float(r['margin']):g} | {r.get('control_limit', 'none')} "
            f"| {r['method']} "
            f"| {r['collisions']}/{r['seeds']} | {r['goals']}/{r['seeds']} "
            f"| {float(r['min_b']):.3f} | {t_goal} |"
        )
    choice = choose(rows)
    verdict = (
        "chosen: no grid point keeps the planner-based methods collision-free"
        if choice is None
        else f"chosen: alpha = {choice[0]:g}, margin = {choice[1]:g} m, control limit {choice[2]}"
    )
    (out / "tuning.md").write_text("\n".join([*lines, "", verdict]) + "\n")
    return verdict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--alpha", default="20,50", help="alpha values")
    parser.add_argument("--margin", default="0.2,0.25,0.3", help="equilibrium margins (m)")
    parser.add_argument(
        "--limit", default="none", help="bounds on |a| and |omega| ('none': unbounded)"
    )
    parser.add_argument("--methods", default=",".join(FILTERED))
    parser.add_argument("--seeds", type=int, default=16, help="tuning seeds per grid point")
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
    jobs = [
        (m, a, g, lim, args.seeds, args.first_seed, args.samples, args.horizon)
        for a, g, lim, m in itertools.product(
            _floats(args.alpha), _floats(args.margin), _limits(args.limit), args.methods.split(",")
        )
    ]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = []
        for row in pool.map(run_point, jobs):
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(write_table(rows, out))


if __name__ == "__main__":
    main()
