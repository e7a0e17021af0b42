"""A grid over a scenario builder's keyword arguments: every configuration is one batch of
seeds (:func:`torchcbf.sweep.evaluate.evaluate`), on the local or the Ray engine."""

from __future__ import annotations

import csv
import itertools
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from torchcbf._checks import check_positive_int
from torchcbf.sweep.engines import check_engine, run_all
from torchcbf.sweep.evaluate import evaluate
from torchcbf.sweep.params import builder, check_keys, describe, jsonable

RATES = ("success", "collision", "goal")


def configurations(grid: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """Every combination of the grid's values, the last key varying fastest."""
    keys = list(grid)
    for key in keys:
        if len(grid[key]) == 0:
            raise ValueError(f"grid[{key!r}] has no values")
    return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*grid.values())]


def run_sweep(
    scenario: str,
    grid: Mapping[str, Sequence[Any]],
    *,
    num_seeds: int = 8,
    seed: int = 0,
    device: str = "cpu",
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    threads: int = 1,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Run every configuration of ``grid`` (``{builder keyword: [values]}``) of
    ``scenario`` on seeds ``seed .. seed + num_seeds - 1``; one row per configuration, in
    grid order (see :func:`~torchcbf.sweep.evaluate.evaluate` for the columns).

    Every configuration is built once with one seed before anything runs, so a bad value
    fails at once with the builder's error. ``engine="ray"`` runs each configuration as a
    Ray task (``address``: join that cluster; otherwise a local one with ``num_cpus``).
    """
    check_keys(scenario, list(grid))
    check_engine(engine)
    check_positive_int("num_seeds", num_seeds)
    check_positive_int("threads", threads)
    configs = configurations(grid)
    make = builder(scenario)
    for params in configs:
        try:
            make(**params, num_seeds=1, seed=seed, device=device)
        except (TypeError, ValueError) as error:
            raise ValueError(f"configuration {describe(params)}: {error}") from error
    calls = [
        {
            "scenario": scenario,
            "params": params,
            "num_seeds": num_seeds,
            "seed": seed,
            "device": device,
            "threads": threads,
        }
        for params in configs
    ]
    return run_all(
        evaluate,
        calls,
        engine=engine,
        address=address,
        num_cpus=num_cpus,
        progress=progress,
        desc=f"sweep {scenario}",
    )


def write_table(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Rows as CSV (tuples written ``a:b``, missing values empty)."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _cell(row.get(k)) for k in columns})
    return path


def _cell(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return ":".join(str(v) for v in value)
    return "" if value is None else value


def write_json(data: Mapping[str, Any], path: Path) -> Path:
    """Strict JSON (no NaN/Infinity literals: they are written as null)."""
    path.write_text(json.dumps(jsonable_tree(data), indent=2, allow_nan=False) + "\n")
    return path


def jsonable_tree(value: Any) -> Any:
    """``value`` with every leaf made strict-JSON (:func:`~torchcbf.sweep.params.jsonable`)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable_tree(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable_tree(v) for v in value]
    return jsonable(value)


def run_info(**extra: Any) -> dict[str, Any]:
    """Versions and settings recorded with every table."""
    from torchcbf import __version__

    return {"torchcbf": __version__, "torch": torch.__version__, **extra}


def plot_sweep(rows: Sequence[Mapping[str, Any]], grid: Mapping[str, Sequence[Any]], path: Path):
    """Success, collision and goal rates (95% intervals) against the first varied grid key,
    one line per combination of the other keys."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    varied = [k for k, v in grid.items() if len(v) > 1] or list(grid)
    x_key = varied[0] if varied else None
    others = [k for k in varied if k != x_key]
    x_values = [jsonable(v) for v in grid[x_key]] if x_key else [None]
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x_values)
    rates = [r for r in RATES if f"{r}_rate" in rows[0]] if rows else []
    fig, axes = plt.subplots(1, len(rates) or 1, figsize=(4.2 * max(len(rates), 1), 3.6))
    axes = list(axes) if len(rates) > 1 else [axes]
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for row in rows:
        label = describe({k: row[k] for k in others}) or "all"
        groups.setdefault(label, []).append(row)
    for ax, rate in zip(axes, rates, strict=False):
        for label, members in groups.items():
            xs = [row[x_key] if x_key else None for row in members]
            pos = xs if numeric else [x_values.index(x) for x in xs]
            y = [row[f"{rate}_rate"] for row in members]
            err = [
                [row[f"{rate}_rate"] - row[f"{rate}_ci95_low"] for row in members],
                [row[f"{rate}_ci95_high"] - row[f"{rate}_rate"] for row in members],
            ]
            ax.errorbar(pos, y, yerr=err, marker="o", capsize=3, label=label)
        if not numeric:
            ax.set_xticks(range(len(x_values)), [_cell(v) for v in x_values], rotation=30)
        ax.set_xlabel(x_key or "configuration")
        ax.set_ylabel(f"{rate} rate (95% CI)")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    if len(groups) > 1:
        axes[0].legend(fontsize=7)
    n = rows[0]["num_seeds"] if rows else 0
    fig.suptitle(f"rates over {n} seeds per configuration")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_sweep(
    rows: Sequence[Mapping[str, Any]],
    grid: Mapping[str, Sequence[Any]],
    out: str | Path,
    **info: Any,
) -> dict[str, Path]:
    """Write ``sweep.csv``, ``sweep.json`` (rows, grid and :func:`run_info`) and
    ``sweep.png`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = {"run": run_info(**info), "grid": dict(grid), "rows": list(rows)}
    return {
        "csv": write_table(rows, out / "sweep.csv"),
        "json": write_json(data, out / "sweep.json"),
        "figure": plot_sweep(rows, grid, out / "sweep.png"),
    }
