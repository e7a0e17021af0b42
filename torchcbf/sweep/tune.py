"""Automatic tuning of a scenario's parameters with Optuna (extra ``tune``).

Each scenario declares its search space in :data:`SEARCH_SPACES` (cost weights,
temperatures, filter parameters: keyword arguments of its builder; a dimension marked
``optional`` is searched only when the builder accepts it). A trial runs the scenario on
the tuning seeds (``seed .. seed + num_seeds - 1``, from 10,000 by default) as one batch and
scores it with :func:`torchcbf.sweep.evaluate.objective` (success rate, ties broken by the
time to goal). The best configuration and the builder's default are then both evaluated on
the evaluation seeds (``0 ..``), which the search never saw.

Trials are asked ``batch`` at a time from a TPE sampler seeded from ``sampler_seed`` and the
trial's number, and told their results as they finish, before the next batch is asked, so a
study is reproducible and the same on the local and the Ray engine (where the trials of a
batch run in parallel as Ray tasks). A trial that raises is recorded as failed (Optuna's
``FAIL`` state, its error in the row) and the study goes on.

Given a run directory (``out``), the study lives in Optuna's SQLite storage ``study.db``
there: every asked trial, its parameters, and its row once finished, are saved as they
happen, and so are the default configuration's row and the final evaluations. ``resume=True``
opens the same study: trials asked but never finished run again with their recorded
parameters, the rest of the study continues, and the outputs equal an uninterrupted run's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from torchcbf import _io
from torchcbf._checks import check_positive_int
from torchcbf.sweep.engines import Outcome, check_engine, ray_session, run_each
from torchcbf.sweep.evaluate import evaluate
from torchcbf.sweep.params import builder, builder_defaults, check_buildable, check_keys, jsonable
from torchcbf.sweep.rundir import RunDir
from torchcbf.sweep.sweep import run_info, write_json, write_table

STORAGE = "study.db"
#: the files a study writes in its run directory (SQLite may add its journal beside the db)
OUTPUTS = (STORAGE, f"{STORAGE}-journal", "study.csv", "best.json", "study.png")
STUDY_NAME = "torchcbf-tune"

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


def tune_settings(
    scenario: str,
    *,
    trials: int,
    num_seeds: int,
    seed: int,
    eval_seed: int,
    fixed: Mapping[str, Any],
    params: Sequence[str] | None,
    sampler_seed: int,
    batch: int,
    device: str,
    threads: int,
) -> dict[str, Any]:
    """What makes two studies the same run (compared by ``resume``; the engine may differ)."""
    return {
        "scenario": scenario,
        "trials": trials,
        "num_seeds": num_seeds,
        "seed": seed,
        "eval_seed": eval_seed,
        "fixed": jsonable(dict(fixed)),
        "params": None if params is None else list(params),
        "sampler_seed": sampler_seed,
        "batch": batch,
        "device": str(device),
        "threads": threads,
    }


def _sampler(optuna: Any, sampler_seed: int, number: int, trials: int, part: int = 0) -> Any:
    """The TPE sampler that draws part ``part`` (0: the ask, ``i + 1``: dimension ``i``) of
    trial ``number``: seeded from ``sampler_seed``, the number and the part, so a resumed
    study draws what an uninterrupted one would, even for a trial cut off between two of its
    parameters."""
    import numpy as np

    seed = int(np.random.SeedSequence([sampler_seed, number, part]).generate_state(1)[0])
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=min(10, trials))


def _suggest_all(
    optuna: Any, study: Any, trial: Any, dims: Sequence[Dimension], **seeds: int
) -> None:
    """Draw every dimension of ``trial`` not drawn yet, each with its own seeded sampler."""
    for i, d in enumerate(dims):
        if d.name not in trial.params:
            study.sampler = _sampler(optuna, part=i + 1, **seeds)
            d.suggest(trial)


def _outcome_row(outcome: Outcome) -> dict[str, Any]:
    if outcome.ok:
        return {**jsonable(outcome.value), "status": "ok"}
    return {"status": "failed", "error": outcome.error}


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
    out: str | Path | RunDir | None = None,
    resume: bool = False,
    overwrite: bool = False,
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
        out: a run directory (path or claimed :class:`RunDir`) for the study's SQLite
            storage and :func:`write_tune`'s files; ``resume``/``overwrite`` as
            :meth:`RunDir.claim` says.

    Returns:
        ``{"best": ..., "default": ..., "evaluation": ..., "trials": [rows], ...}``: the best
        parameters and objective, the default configuration's objective on the same tuning
        seeds, both re-run on the evaluation seeds, and one row per trial (``status``
        ``"ok"``, or ``"failed"`` with its ``error``). ``best`` is None when every trial
        failed.
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
    check_buildable(scenario, [fixed], seed=seed, device=device)
    settings = tune_settings(
        scenario,
        trials=trials,
        num_seeds=num_seeds,
        seed=seed,
        eval_seed=eval_seed,
        fixed=fixed,
        params=params,
        sampler_seed=sampler_seed,
        batch=batch,
        device=device,
        threads=threads,
    )
    run = out
    if out is not None and not isinstance(out, RunDir):
        run = RunDir.claim(out, kind="tune", settings=settings, resume=resume,
                           overwrite=overwrite, outputs=OUTPUTS)  # fmt: skip
    storage: Any = None
    if run is not None:
        storage = optuna.storages.RDBStorage(f"sqlite:///{run.path / STORAGE}")
    study = optuna.create_study(
        direction="maximize",
        sampler=_sampler(optuna, sampler_seed, 0, trials),
        storage=storage,
        study_name=STUDY_NAME,
        load_if_exists=True,
    )
    common = {"num_seeds": num_seeds, "device": device, "threads": threads}

    def call(arguments: Mapping[str, Any], first_seed: int) -> dict[str, Any]:
        return {
            "scenario": scenario,
            "params": {**fixed, **arguments},
            "seed": first_seed,
            **common,
        }

    options = {"engine": engine, "address": address, "num_cpus": num_cpus, "progress": False}

    def evaluate_once(key: str, arguments: Mapping[str, Any], first_seed: int) -> dict:
        """The row of one configuration, kept in the study so a resumed run reuses it."""
        if key not in study.user_attrs:
            outcomes: list[Outcome] = []
            run_each(
                evaluate, [call(arguments, first_seed)], lambda i, o: outcomes.append(o), **options
            )
            study.set_user_attr(key, _outcome_row(outcomes[0]))
        return dict(study.user_attrs[key])

    session = ray_session(address, num_cpus) if engine == "ray" else contextlib.nullcontext()
    desc = f"tune {scenario} ({engine})"
    with session, tqdm(total=trials + 3, desc=desc, disable=not progress) as bar:
        default_row = evaluate_once("default_row", {}, seed)
        bar.update(1)
        for start in range(0, trials, batch):
            numbers = range(start, min(start + batch, trials))
            known = {t.number: t for t in study.get_trials(deepcopy=False)}
            for number in numbers:
                seeds = {"sampler_seed": sampler_seed, "number": number, "trials": trials}
                if number not in known:  # asked in order: every earlier trial exists
                    study.sampler = _sampler(optuna, **seeds)
                    trial = study.ask()
                    if trial.number != number:
                        raise RuntimeError(f"the study asked trial {trial.number}, not {number}")
                    _suggest_all(optuna, study, trial, dims, **seeds)
                elif not known[number].state.is_finished() and set(known[number].params) != {
                    d.name for d in dims
                }:  # cut off while its parameters were drawn: the rest are drawn now
                    trial = optuna.trial.Trial(study, known[number]._trial_id)
                    _suggest_all(optuna, study, trial, dims, **seeds)
            known = {t.number: t for t in study.get_trials(deepcopy=False)}
            pending = [n for n in numbers if not known[n].state.is_finished()]
            bar.update(len(numbers) - len(pending))
            arguments = [_arguments(dims, known[n].params) for n in pending]

            def finished(i: int, outcome: Outcome, pending: list[int] = pending) -> None:
                number = pending[i]
                study.set_user_attr(f"row_{number}", _outcome_row(outcome))
                if outcome.ok:
                    study.tell(number, outcome.value["objective"])
                else:
                    study.tell(number, state=optuna.trial.TrialState.FAIL)
                bar.update(1)
                if run is not None:
                    write_table(_trial_rows(study, trials), run.path / "study.csv")

            run_each(evaluate, [call(a, seed) for a in arguments], finished, **options)
        rows = _trial_rows(study, trials)
        complete = [
            t for t in study.get_trials(deepcopy=False) if t.number < trials and t.value is not None
        ]
        best = max(complete, key=lambda t: (t.value, -t.number)) if complete else None
        best_arguments = _arguments(dims, best.params) if best is not None else None
        evaluation = {"best": None, "default": None}
        if best is not None:
            evaluation["best"] = evaluate_once(
                f"evaluation_best_{best.number}", best_arguments, eval_seed
            )
        evaluation["default"] = evaluate_once("evaluation_default", {}, eval_seed)
        bar.update(2)
    defaults = {**builder_defaults(scenario), **fixed}
    make = builder(scenario)

    def resolved(arguments: Mapping[str, Any]) -> dict[str, Any]:
        """Every parameter the scenario used (``Scenario.params``), where it records them."""
        built = make(**arguments, num_seeds=1, seed=seed, device=device)
        params = getattr(built, "params", None) or {}
        return {k: v for k, v in params.items() if k not in ("num_seeds", "seed")}

    result = {
        "scenario": scenario,
        "fixed": fixed,
        "space": {d.name: d.describe() for d in dims},
        "tuning_seeds": {"first": seed, "count": num_seeds},
        "evaluation_seeds": {"first": eval_seed, "count": num_seeds},
        "sampler": {"name": "TPESampler", "seed": sampler_seed, "batch": batch},
        "objective": "success rate + tie-break / (2 seeds) (torchcbf.sweep.evaluate)",
        "best": None
        if best is None
        else {
            "trial": best.number,
            "params": best.params,
            "arguments": {**fixed, **best_arguments},
            "resolved": resolved({**fixed, **best_arguments}),
            "objective": best.value,
        },
        "default": {
            "arguments": defaults,
            "resolved": resolved(fixed),
            "objective": default_row.get("objective"),
        },
        "evaluation": evaluation,
        "failed_trials": [r["trial"] for r in rows if r["status"] == "failed"],
        "trials": rows,
    }
    if run is not None:
        paths = write_tune(result, run.path, engine=engine, device=device)
        run.record(STORAGE, *paths.values())
        run.finish()
    return result


def _trial_rows(study: Any, trials: int) -> list[dict[str, Any]]:
    """One row per finished trial, by number: its parameters and its evaluation row."""
    rows = []
    attrs = study.user_attrs
    for t in sorted(study.get_trials(deepcopy=False), key=lambda t: t.number):
        row = attrs.get(f"row_{t.number}")
        if t.number >= trials or not t.state.is_finished() or row is None:
            continue
        rows.append(
            {
                "trial": t.number,
                **{k: jsonable(v) for k, v in t.params.items()},
                **row,
            }
        )
    return rows


def plot_study(
    rows: Sequence[Mapping[str, Any]], default_objective: float | None, path: Path
) -> Path:
    """Objective per trial, the best so far, and the default configuration's objective
    (failed trials left out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r.get("objective") is not None]
    x = [r["trial"] for r in rows]
    y = [r["objective"] for r in rows]
    best = [max(y[: i + 1]) for i in range(len(y))]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(x, y, "o", label="trial")
    ax.step(x, best, where="post", label="best so far")
    if default_objective is not None:
        ax.axhline(default_objective, color="gray", ls="--", label="default configuration")
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (success rate + tie-break)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _io.save_figure(fig, path)


def write_tune(result: Mapping[str, Any], out: str | Path, **info: Any) -> dict[str, Path]:
    """Write ``best.json`` (everything but the trial rows), ``study.csv`` (one row per
    trial) and ``study.png`` into ``out`` (each file atomically)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {k: v for k, v in result.items() if k != "trials"}
    rows = result["trials"]
    return {
        "json": write_json({"run": run_info(**info), **jsonable(summary)}, out / "best.json"),
        "csv": write_table(rows, out / "study.csv"),
        "figure": plot_study(rows, result["default"]["objective"], out / "study.png"),
    }
