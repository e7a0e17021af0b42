"""A grid over a scenario builder's keyword arguments: every configuration is one batch of
seeds (:func:`torchcbf.sweep.evaluate.evaluate`), on the local or the Ray engine.

Given a run directory (``out``), a sweep records each configuration as it finishes: one line
of the append-only ``sweep.jsonl`` (the journal), then ``sweep.json`` and ``sweep.csv``
rewritten atomically with every row so far (``"complete": false`` until the end, when
``sweep.png`` is drawn). ``resume=True`` reads the journal back and runs only the
configurations it does not hold. A configuration that raises is a row with ``status``
``"failed"`` and its ``error``; the others run on (and ``resume`` does not run it again).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torchcbf import _io
from torchcbf._checks import check_positive_int
from torchcbf.scenarios import get
from torchcbf.sim import run_info, strict
from torchcbf.sweep.engines import Outcome, check_engine, run_each
from torchcbf.sweep.evaluate import evaluate
from torchcbf.sweep.params import (
    ScenarioName,
    check_buildable,
    check_keys,
    check_seeds,
    describe,
)
from torchcbf.sweep.rundir import RunDir, owned

JOURNAL = "sweep.jsonl"
#: the files a sweep writes in its run directory
OUTPUTS = (JOURNAL, "sweep.json", "sweep.csv", "sweep.png")

RATES = ("success", "collision", "goal")


def configurations(grid: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """Every combination of the grid's values, the last key varying fastest. Each value is
    a list (a tuple, a range, a 1-D array) of values: a single value, a string or a set (no
    order) too, raises naming it, as does a value that is not finite (the run's files, JSON,
    could not tell it from another)."""
    if not isinstance(grid, Mapping):
        raise TypeError(f"grid must map parameter names to lists of values, got {grid!r}")
    keys = list(grid)
    for key in keys:
        values = grid[key]
        ordered = isinstance(values, Sequence) or getattr(values, "ndim", None) == 1
        if isinstance(values, (str, bytes)) or not ordered:
            raise TypeError(
                f"grid[{key!r}] must be a list of values, got {values!r} (write [{values!r}])"
            )
        if len(values) == 0:
            raise ValueError(f"grid[{key!r}] has no values")
        for value in values:
            if not _finite(value):
                raise ValueError(f"grid[{key!r}] holds {value!r}, which is not finite")
    return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*grid.values())]


def _finite(value: Any) -> bool:
    """Whether no number in ``value`` (a number, or a tuple or list of them) is NaN or
    infinite."""
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    if isinstance(value, numbers.Real) or getattr(value, "ndim", None) == 0:
        return math.isfinite(float(value))
    return True


def sweep_settings(
    scenario: ScenarioName,
    grid: Mapping[str, Sequence[Any]],
    *,
    num_seeds: int,
    seed: int,
    device: str,
    threads: int,
) -> dict[str, Any]:
    """What makes two sweeps the same run (compared by ``resume``; the engine may differ,
    its numbers are the same): the parameters held at their defaults included, so a sweep
    is not resumed across a change of defaults."""
    return {
        "scenario": get(scenario).name,
        "grid": strict(dict(grid)),
        "fixed": strict(fixed_parameters(scenario, grid)),
        "num_seeds": num_seeds,
        "seed": seed,
        "device": str(device),
        "threads": threads,
    }


def run_sweep(
    scenario: ScenarioName,
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
    out: str | Path | RunDir | None = None,
    resume: bool = False,
    overwrite: bool = False,
) -> list[dict[str, Any]]:
    """Run every configuration of ``grid`` (``{parameter: [values]}``) of ``scenario`` (a
    registered name or a :class:`~torchcbf.scenarios.ScenarioEntry`) on seeds ``seed ..
    seed + num_seeds - 1``; one row per configuration, in
    grid order (see :func:`~torchcbf.sweep.evaluate.evaluate` for the columns), with
    ``status`` ``"ok"``, or ``"failed"`` and the ``error`` of a configuration that raised.

    Every configuration is built once with one seed before anything runs, so a bad value
    fails at once with the builder's error. ``engine="ray"`` runs each configuration as a
    Ray task (``address``: join that cluster; otherwise a local one with ``num_cpus``).
    ``out``: a run directory (a path, claimed with ``resume``/``overwrite`` as
    :meth:`RunDir.claim` says, or a claimed :class:`RunDir`) where each row is written as
    it finishes, then the table and the figure (see the module docstring).
    """
    entry = get(scenario)
    check_keys(entry, list(grid))
    check_engine(engine)
    check_positive_int("num_seeds", num_seeds)
    seed = check_seeds(seed, num_seeds)
    check_positive_int("threads", threads)
    configs = configurations(grid)
    check_buildable(entry, configs, seed=seed, device=device)
    settings = sweep_settings(
        entry, grid, num_seeds=num_seeds, seed=seed, device=device, threads=threads
    )
    run = out
    if out is not None and not isinstance(out, RunDir):
        run = RunDir.claim(out, kind="sweep", settings=settings, resume=resume,
                           overwrite=overwrite, outputs=OUTPUTS)  # fmt: skip
    with owned(run, out):
        calls = [
            {
                "scenario": entry,
                "params": params,
                "num_seeds": num_seeds,
                "seed": seed,
                "device": device,
                "threads": threads,
            }
            for params in configs
        ]
        done: dict[int, dict[str, Any]] = {}
        info = {
            "scenario": entry.name,
            "fixed": fixed_parameters(entry, grid),
            "num_seeds": num_seeds,
            "first_seed": seed,
            "engine": engine,
            "device": device,
            "torch_threads": threads,  # what each configuration ran with
        }
        if run is not None and run.resumed:
            done = read_journal(run.path / JOURNAL, configs)
            _trim_journal(run.path / JOURNAL)

        def finished(i: int, outcome: Outcome) -> None:
            row = _row(configs[i], num_seeds, seed, outcome)
            done[i] = row
            if run is not None:
                line = json.dumps({"index": i, "row": strict(row)}, allow_nan=False)
                _io.append_line(run.path / JOURNAL, line)
                rows = [done[k] for k in sorted(done)]
                _write_rows(rows, grid, run.path, complete=False, **info)

        todo = [i for i in range(len(configs)) if i not in done]
        run_each(
            evaluate,
            [calls[i] for i in todo],
            lambda j, outcome: finished(todo[j], outcome),
            engine=engine,
            address=address,
            num_cpus=num_cpus,
            progress=progress,
            desc=f"sweep {entry.name}",
        )
        rows = [done[i] for i in range(len(configs))]
        if run is not None:
            paths = write_sweep(rows, grid, run.path, **info)
            run.record(JOURNAL, *paths.values())
            run.finish()
        return rows


def fixed_parameters(scenario: ScenarioName, grid: Mapping[str, Sequence[Any]]) -> dict:
    """The scenario's parameters a sweep over ``grid`` holds at their defaults."""
    return {k: v for k, v in get(scenario).defaults().items() if k not in grid}


def _row(params: Mapping[str, Any], num_seeds: int, seed: int, outcome: Outcome) -> dict[str, Any]:
    if outcome.ok:
        return {**outcome.value, "status": "ok"}
    return {
        **{k: strict(v) for k, v in params.items()},
        "num_seeds": num_seeds,
        "first_seed": seed,
        "status": "failed",
        "error": outcome.error,
    }


def read_journal(
    path: Path, configs: Sequence[Mapping[str, Any]] | None = None
) -> dict[int, dict[str, Any]]:
    """``{grid index: row}`` of the configurations a sweep's journal records as finished (a
    last line cut by a kill is left out). With ``configs``, a row is found by its
    parameters, whatever index it was written under (the same grid given in another order
    of its keys), and rows of no configuration of ``configs`` are left out."""
    where: dict[str, list[int]] = {}
    for i, config in enumerate(configs or ()):
        where.setdefault(_key(config, config), []).append(i)  # a repeated point: every index
    done: dict[int, dict[str, Any]] = {}
    for line in _io.read_lines(path):
        try:
            entry = json.loads(line)
            i, row = int(entry["index"]), dict(entry["row"])
        except (ValueError, KeyError, TypeError):
            continue
        if configs is None:
            done[i] = row
        elif configs:
            for j in where.get(_key(row, configs[0]), ()):
                done[j] = row
    return done


def _key(values: Mapping[str, Any], config: Mapping[str, Any]) -> str:
    """The parameters of ``config`` as ``values`` holds them, in one canonical text (a
    number as a float: ``1`` and ``1.0`` are one point, as the run's settings compare)."""

    def canonical(v: Any) -> Any:
        v = strict(v)
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v

    return json.dumps({k: canonical(values.get(k)) for k in config}, sort_keys=True)


def _trim_journal(path: Path) -> None:
    """Cut a last line left incomplete by a kill, so the next line starts on its own."""
    if not path.exists():
        return
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    if end < len(data):
        with path.open("r+b") as f:
            f.truncate(end)


def _write_rows(
    rows: Sequence[Mapping[str, Any]],
    grid: Mapping[str, Sequence[Any]],
    out: Path,
    *,
    complete: bool,
    **info: Any,
) -> dict[str, Path]:
    data = {"run": run_info(**info), "grid": dict(grid), "complete": complete, "rows": list(rows)}
    return {
        "csv": write_table(rows, out / "sweep.csv"),
        "json": write_json(data, out / "sweep.json"),
    }


def write_table(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Rows as CSV (tuples written ``a:b``, missing values empty)."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row.get(k)) for k in columns})
    return _io.write_text(path, text.getvalue())


def _cell(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return ":".join(str(v) for v in value)
    return "" if value is None else value


def write_json(data: Mapping[str, Any], path: Path) -> Path:
    """Strict JSON (:func:`torchcbf.sim.strict`: no NaN/Infinity literals, written as null)."""
    return _io.write_json(path, strict(data))


def plot_sweep(rows: Sequence[Mapping[str, Any]], grid: Mapping[str, Sequence[Any]], path: Path):
    """Success, collision and goal rates (95% intervals) against the first varied grid key,
    one line per combination of the other keys."""
    import matplotlib.pyplot as plt  # the user's backend stays (no display: Agg)

    varied = [k for k, v in grid.items() if len(v) > 1] or list(grid)
    x_key = varied[0] if varied else None
    others = [k for k in varied if k != x_key]
    x_values = [strict(v) for v in grid[x_key]] if x_key else [None]
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x_values)
    rows = [row for row in rows if row.get("status", "ok") == "ok"]  # failed rows: no rates
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
    return _io.save_figure(fig, path)


def write_sweep(
    rows: Sequence[Mapping[str, Any]],
    grid: Mapping[str, Sequence[Any]],
    out: str | Path,
    **info: Any,
) -> dict[str, Path]:
    """Write a finished sweep into ``out``: ``sweep.csv``, ``sweep.json`` (rows, grid,
    ``"complete": true`` and :func:`run_info` with ``info``, e.g. the fixed parameters) and
    ``sweep.png``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = _write_rows(rows, grid, out, complete=True, **info)
    paths["figure"] = plot_sweep(rows, grid, out / "sweep.png")
    return paths
