"""Automatic tuning of a scenario's parameters with Optuna (extra ``tune``).

Each scenario declares its search space in :data:`SEARCH_SPACES` (cost weights,
temperatures, filter parameters: keyword arguments of its builder; a dimension marked
``optional`` is searched only when the builder accepts it). A trial runs the scenario on
the tuning seeds (``seed .. seed + num_seeds - 1``, from 10,000 by default) as one batch and
scores it with :func:`torchcbf.sweep.evaluate.objective` (success rate, ties broken by the
time to goal). The best configuration and the builder's default are then both evaluated on
the evaluation seeds (``0 ..``), which the search never saw.

Trials are asked ``batch`` at a time from a seeded TPE sampler and told their results in
order, so a study is reproducible and the same on the local and the Ray engine (where the
trials of a batch run in parallel as Ray tasks).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from torchcbf._checks import check_positive_int
from torchcbf.sweep.engines import check_engine, ray_session, run_all
from torchcbf.sweep.evaluate import evaluate
from torchcbf.sweep.params import builder, builder_defaults, check_keys
from torchcbf.sweep.sweep import jsonable_tree, run_info, write_json, write_table

TUNING_SEED = 10_000


@dataclass(frozen=True)
class Dimension:
    """One searched parameter.

    ``kind``: ``"float"``, ``"int"`` or ``"categorical"`` (``choices``); ``argument``: the
    builder keyword it sets (default: ``name``); ``to_argument`` maps the sampled value to
    the keyword's value; ``optional``: skipped when the builder has no such keyword;
    ``skip_methods``: values of the builder's ``method`` for which the dimension has no
    effect (an MPPI parameter for the filter alone, a filter parameter for MPPI alone).
    """

    name: str
    kind: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    choices: tuple[Any, ...] = ()
    argument: str | None = None
    to_argument: Callable[[Any], Any] | None = field(default=None, compare=False)
    optional: bool = False
    skip_methods: tuple[str, ...] = ()

    @property
    def keyword(self) -> str:
        """The builder keyword this dimension sets."""
        return self.argument or self.name

    def suggest(self, trial: Any) -> Any:
        """The trial's value of this dimension."""
        if self.kind == "float":
            return trial.suggest_float(self.name, self.low, self.high, log=self.log)
        if self.kind == "int":
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        if self.kind == "categorical":
            return trial.suggest_categorical(self.name, list(self.choices))
        raise ValueError(f"Dimension.kind must be float, int or categorical, got {self.kind!r}")

    def describe(self) -> dict[str, Any]:
        """The dimension as JSON."""
        if self.kind == "categorical":
            return {"kind": self.kind, "choices": list(self.choices), "argument": self.keyword}
        return {
            "kind": self.kind,
            "low": self.low,
            "high": self.high,
            "log": self.log,
            "argument": self.keyword,
        }


def _omega_weight(w: float) -> tuple[float, float]:
    return (1.0, float(w))


_NO_PLANNER = ("scbf",)
_NO_FILTER = ("mppi",)

SEARCH_SPACES: dict[str, tuple[Dimension, ...]] = {
    # Scenario A: MPPI's sampling and its temperature / control cost where the builder
    # exposes them.
    "reach-avoid": (
        Dimension("num_samples", "int", 256, 10_000, log=True),
        Dimension("horizon", "int", 20, 60),
        Dimension("temperature", "float", 1e-3, 1.0, log=True, optional=True),
        Dimension("noise_sigma", "float", 0.5, 16.0, log=True, optional=True),
        Dimension("control_cost_weight", "float", 1e-3, 1.0, log=True, optional=True),
    ),
    # Scenario B: the stochastic CBF's free parameters (rectification gain, barrier scale,
    # the QP's weight on omega, and alpha/beta/margin where the builder takes them) and
    # MPPI's noise and temperature.
    "mppi-cbf": (
        Dimension("rectify_gain", "float", 1.0, 100.0, log=True, skip_methods=_NO_FILTER),
        Dimension("barrier_scale", "float", 1e-3, 1.0, log=True, skip_methods=_NO_FILTER),
        Dimension(
            "control_weight_omega",
            "float",
            1e-4,
            1.0,
            log=True,
            argument="control_weight",
            to_argument=_omega_weight,
            skip_methods=_NO_FILTER,
        ),
        Dimension("noise_sigma", "float", 1.0, 16.0, log=True, skip_methods=_NO_PLANNER),
        Dimension("alpha", "float", 0.5, 100.0, log=True, optional=True, skip_methods=_NO_FILTER),
        Dimension("beta", "float", 0.0, 2.0, optional=True, skip_methods=_NO_FILTER),
        Dimension("margin", "float", 0.0, 0.5, optional=True, skip_methods=_NO_FILTER),
        Dimension(
            "temperature", "float", 1e-3, 1.0, log=True, optional=True, skip_methods=_NO_PLANNER
        ),
    ),
}


def search_space(
    scenario: str, names: Sequence[str] | None = None, fixed: Mapping[str, Any] | None = None
) -> list[Dimension]:
    """The dimensions of ``scenario`` the builder accepts and its ``method`` (from ``fixed``
    or the builder's default) uses, restricted to ``names`` if given, without those whose
    keyword is in ``fixed``."""
    if scenario not in SEARCH_SPACES:
        raise ValueError(f"scenario must be one of {sorted(SEARCH_SPACES)}, got {scenario!r}")
    accepted = builder_defaults(scenario)
    method = {**accepted, **(fixed or {})}.get("method")
    dims = [
        d
        for d in SEARCH_SPACES[scenario]
        if (d.keyword in accepted or not d.optional) and method not in d.skip_methods
    ]
    if names is not None:
        known = {d.name for d in dims}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {unknown} in the search space of {scenario!r}; "
                f"it has: {', '.join(sorted(known))}"
            )
        dims = [d for d in dims if d.name in names]
    dims = [d for d in dims if d.keyword not in (fixed or {})]
    if not dims:
        raise ValueError(f"nothing to search for {scenario!r}: every dimension is fixed")
    return dims


def _arguments(dims: Sequence[Dimension], values: Mapping[str, Any]) -> dict[str, Any]:
    out = {}
    for d in dims:
        v = values[d.name]
        out[d.keyword] = d.to_argument(v) if d.to_argument is not None else v
    return out


def tune(
    scenario: str,
    *,
    trials: int = 20,
    num_seeds: int = 8,
    seed: int = TUNING_SEED,
    eval_seed: int = 0,
    fixed: Mapping[str, Any] | None = None,
    params: Sequence[str] | None = None,
    sampler_seed: int = 0,
    batch: int = 2,
    device: str = "cpu",
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    threads: int = 1,
    progress: bool = True,
) -> dict[str, Any]:
    """Search ``scenario``'s space (:func:`search_space`) for ``trials`` trials.

    Args:
        num_seeds: seeds per trial, run as one batch.
        seed: first tuning seed; ``eval_seed``: first evaluation seed (the two ranges must
            not overlap).
        fixed: builder keywords held fixed (e.g. ``{"method": "scbf"}``).
        params: the dimensions to search (default: all of the space the builder accepts).
        sampler_seed: seed of Optuna's TPE sampler.
        batch: trials asked before their results are told (run in parallel on Ray).

    Returns:
        ``{"best": ..., "default": ..., "evaluation": ..., "trials": [rows], ...}``: the best
        parameters and objective, the default configuration's objective on the same tuning
        seeds, both re-run on the evaluation seeds, and one row per trial.
    """
    try:
        import optuna
    except ImportError as error:
        raise ImportError('tune needs Optuna: pip install "torchcbf[tune]"') from error
    fixed = dict(fixed or {})
    check_keys(scenario, list(fixed))
    check_engine(engine)
    for name, value in (("trials", trials), ("num_seeds", num_seeds), ("batch", batch)):
        check_positive_int(name, value)
    if max(seed, eval_seed) < min(seed, eval_seed) + num_seeds:
        raise ValueError(
            f"tuning seeds {seed}.. and evaluation seeds {eval_seed}.. overlap "
            f"({num_seeds} seeds each)"
        )
    dims = search_space(scenario, params, fixed)
    sampler = optuna.samplers.TPESampler(seed=sampler_seed, n_startup_trials=min(10, trials))
    study = optuna.create_study(direction="maximize", sampler=sampler)
    common = {"num_seeds": num_seeds, "device": device, "threads": threads}

    def call(arguments: Mapping[str, Any], first_seed: int) -> dict[str, Any]:
        return {
            "scenario": scenario,
            "params": {**fixed, **arguments},
            "seed": first_seed,
            **common,
        }

    rows: list[dict[str, Any]] = []
    run = {"engine": engine, "address": address, "num_cpus": num_cpus, "progress": False}
    session = ray_session(address, num_cpus) if engine == "ray" else _nothing()
    desc = f"tune {scenario} ({engine})"
    with session, tqdm(total=trials + 3, desc=desc, disable=not progress) as bar:
        (default_row,) = run_all(evaluate, [call({}, seed)], **run)
        bar.update(1)
        while len(rows) < trials:
            asked = [study.ask() for _ in range(min(batch, trials - len(rows)))]
            arguments = [_arguments(dims, {d.name: d.suggest(t) for d in dims}) for t in asked]
            results = run_all(evaluate, [call(a, seed) for a in arguments], **run)
            for trial, result in zip(asked, results, strict=True):
                study.tell(trial, result["objective"])
                rows.append({"trial": trial.number, **trial.params, **result})
                bar.update(1)
        best = study.best_trial
        best_arguments = _arguments(dims, best.params)
        evaluation = run_all(
            evaluate, [call(best_arguments, eval_seed), call({}, eval_seed)], **run
        )
        bar.update(2)
    defaults = {**builder_defaults(scenario), **fixed}
    make = builder(scenario)

    def resolved(arguments: Mapping[str, Any]) -> dict[str, Any]:
        """Every parameter the scenario used (``Scenario.params``), where it records them."""
        built = make(**arguments, num_seeds=1, seed=seed, device=device)
        params = getattr(built, "params", None) or {}
        return {k: v for k, v in params.items() if k not in ("num_seeds", "seed")}

    return {
        "scenario": scenario,
        "fixed": fixed,
        "space": {d.name: d.describe() for d in dims},
        "tuning_seeds": {"first": seed, "count": num_seeds},
        "evaluation_seeds": {"first": eval_seed, "count": num_seeds},
        "sampler": {"name": "TPESampler", "seed": sampler_seed, "batch": batch},
        "objective": "success rate + tie-break / (2 seeds) (torchcbf.sweep.evaluate)",
        "best": {
            "trial": best.number,
            "params": best.params,
            "arguments": {**fixed, **best_arguments},
            "resolved": resolved({**fixed, **best_arguments}),
            "objective": best.value,
        },
        "default": {
            "arguments": defaults,
            "resolved": resolved(fixed),
            "objective": default_row["objective"],
        },
        "evaluation": {"best": evaluation[0], "default": evaluation[1]},
        "trials": rows,
    }


class _nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: Any) -> None:
        return None


def plot_study(rows: Sequence[Mapping[str, Any]], default_objective: float, path: Path) -> Path:
    """Objective per trial, the best so far, and the default configuration's objective."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["trial"] for r in rows]
    y = [r["objective"] for r in rows]
    best = [max(y[: i + 1]) for i in range(len(y))]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(x, y, "o", label="trial")
    ax.step(x, best, where="post", label="best so far")
    ax.axhline(default_objective, color="gray", ls="--", label="default configuration")
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (success rate + tie-break)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_tune(result: Mapping[str, Any], out: str | Path, **info: Any) -> dict[str, Path]:
    """Write ``best.json`` (everything but the trial rows), ``study.csv`` (one row per
    trial) and ``study.png`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {k: v for k, v in result.items() if k != "trials"}
    rows = result["trials"]
    return {
        "json": write_json({"run": run_info(**info), **jsonable_tree(summary)}, out / "best.json"),
        "csv": write_table(rows, out / "study.csv"),
        "figure": plot_study(rows, result["default"]["objective"], out / "study.png"),
    }
